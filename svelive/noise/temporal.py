"""Noise samples from consecutive frames at static pixels: the difference of two frames removes the scene
altogether (variance ``2 (s / g + R)``), whatever its texture (:func:`temporal_samples`,
:func:`triple_samples`); :func:`pair_fit` is the line of one pair."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from svelive.core.sensor import DEFAULT_FULL_WELL_E, DEFAULT_READ_NOISE_E, Sensor
from svelive.memory import outside_heap
from svelive.noise.inputs import _fixed, _high_level
from svelive.noise.model import QUANTISATION_VARIANCE, EstimatorConfig, LineFit, NoiseSamples
from svelive.noise.stats import _bin_index, bin_samples, fit_line


def _strided(size: int, max_samples: int) -> int:
    """Every how many pixels in raster order to sample a frame of ``size`` pixels: at least
    ``size / max_samples``, and prime to 2, 3, 5 and 7 so that every tile phase (every exposure) is
    sampled (a step shared with the tile would keep one exposure only)."""
    need = max(1, int(math.ceil(size / max_samples)))
    return next(k for k in range(need, need + 210) if math.gcd(k, 210) == 1)


def _grouped(signal: np.ndarray, by: np.ndarray) -> np.ndarray:
    """Each sample's group mean of ``signal`` (float64 (N,)), the groups cut from ``by`` (float (N,), DN):
    1 DN wide below 256 DN, 1 % wide above."""
    group = np.where(by < 256.0, np.floor(by), 256.0 + np.floor(np.log(np.maximum(by, 256.0) / 256.0) / np.log(1.01)))
    _, index = np.unique(group, return_inverse=True)
    return (np.bincount(index, weights=signal) / np.bincount(index))[index]


def _clear_of_clipping(by: np.ndarray, floor: float, high: float, model: tuple[float, float]) -> np.ndarray:
    """bool (N,): values ``by`` (DN) four noise standard deviations (under ``model``) clear of both clip levels."""
    slope, intercept = model
    sd = np.sqrt(np.maximum(slope * np.maximum(by, 0.0) + intercept, QUANTISATION_VARIANCE))
    return (by - floor >= 4.0 * sd) & (by + 4.0 * sd < high)


def _difference_samples(a: np.ndarray, b: np.ndarray, k: float, t: np.ndarray) -> NoiseSamples:
    """Samples ``u = (a - k b)^2 / (1 + k^2)`` (float64 (N,), the readings of two frames of a static scene,
    ``k`` their brightness ratio) with their signal coordinates ``t``: ``E[u] = t / g + R``."""
    d = a - k * b
    return NoiseSamples(t=t, u=d * d / (1.0 + k * k))


def temporal_samples(previous: np.ndarray, current: np.ndarray, static: np.ndarray | None, floor: float,
                     high: float, model: tuple[float, float], max_samples: int = 100_000,
                     period: tuple[int, int] | None = None) -> NoiseSamples:
    """Samples from two frames' signals (float (H, W), DN above black) at static pixels.

    ``d = x1 - k x2`` has variance ``(1 + k^2) (s / g + R)`` where the scene did not change (``k``
    removes a global brightness change, flicker), whatever the texture. The pixels are grouped by
    their neighbours one tile (``period``, rows and columns) to the left and right, both frames
    averaged: a value whose noise is independent of the pixel's. Within any group so chosen the
    mean of ``d^2 / (1 + k^2)`` is ``E[s | group] / g + R`` and the mean of ``(x1 + k x2) / 2`` is
    ``E[s | group]``, exactly, for any noise distribution and any texture (the variance is linear in
    the signal). Without a ``period`` (a layout not known: neighbours may have other exposures,
    and groups that mix them follow the signal too loosely to fit a line) the pixels are grouped by
    the pair's own mean, corrected for its noise by :func:`_tweedie`: grouping by a noisy value
    dilutes the slope where pixels crowd the dark end, and the correction, exact only for Gaussian
    noise of one variance, reads a low read noise beside strong shot noise 10-20 % high. A pixel is
    dropped when its pair's mean lies within four noise standard deviations (under ``model``,
    ``(slope, intercept)``) of a clip level, not by either reading: dropping readings
    at 0 or at white truncates their noise (the low read noise the older pair estimate gave with a
    black level of 0), while the mean is independent of the difference (Gaussian noise). Its
    neighbours may clip: they only choose the group.
    """
    h, w = np.shape(previous)
    first, second = np.asarray(previous).ravel(), np.asarray(current).ravel()
    idx = np.arange(0, h * w, _strided(h * w, max_samples))
    a, b = first[idx].astype(np.float64), second[idx].astype(np.float64)
    mask = None if static is None else np.asarray(static, bool).ravel()
    keep = np.ones(a.shape, bool) if mask is None else mask[idx]
    sums = _static_sums([first, second], mask)
    k = sums[0] / sums[1] if sums[1] > 0 else 1.0
    mean = 0.5 * (a + k * b)
    if period is None:
        var_mean = 0.5 * np.maximum(model[0] * np.maximum(mean, 0.0) + model[1], QUANTISATION_VARIANCE)
        signal = _tweedie(mean, var_mean, keep)  # from the density of all pixels, before any cut
        keep &= _clear_of_clipping(mean, floor, high, model)
        if keep.sum() < 100:
            return NoiseSamples(np.zeros(0), np.zeros(0))
        return _difference_samples(a[keep], b[keep], k, signal[keep])
    pw = period[1] if w > period[1] else 1
    x = idx % w
    left, right = x >= pw, x + pw < w
    by = np.zeros(idx.size)
    for side, at in ((left, idx - pw), (right, idx + pw)):  # the neighbours' pair means, where they exist
        j = at[side]
        by[side] += 0.5 * (first[j].astype(np.float64) + k * second[j].astype(np.float64))
    by /= np.maximum(left.astype(np.float64) + right, 1.0)
    keep &= (left | right) & _clear_of_clipping(mean, floor, high, model)
    if keep.sum() < 100:
        return NoiseSamples(np.zeros(0), np.zeros(0))
    return _difference_samples(a[keep], b[keep], k, _grouped(mean[keep], by[keep]))


def _static_sums(frames: list[np.ndarray], static: np.ndarray | None, chunk: int = 1 << 18) -> list[float]:
    """The sum of each frame (float (N,), DN) over every static pixel (bool (N,), None: all), float64.

    Their ratios remove a global change of brightness (flicker) from frame differences. Taken over
    the pixels sampled rather than all, a ratio's own noise (about 1 % at 50 000 pixels of a dim frame)
    puts ``(1 - k)^2 s^2`` into every difference: nothing at the dark end, a variance twice the noise's
    at the bright end of a dim frame, where the gain is read (40 000 e- / 6 DN, 7 stops dark: the
    gain 20 % low after 16 runs).

    The static pixels of each frame go to one buffer outside malloc's heap (``svelive.memory.outside_heap``):
    a whole frame's worth, made only while a stream's noise tracker reads a run, which the heap would keep."""
    if static is None:
        return [float(np.sum(x, dtype=np.float64)) for x in frames]
    count, kept, sums = int(np.count_nonzero(static)), None, []
    for x in frames:
        if kept is None or kept.dtype != x.dtype:
            kept = outside_heap((count,), x.dtype)
        at = 0
        for start in range(0, x.size, chunk):  # x[static], a chunk at a time (np.compress indexes by intp)
            part = x[start:start + chunk][static[start:start + chunk]]
            kept[at:at + part.size] = part
            at += part.size
        sums.append(float(np.sum(kept, dtype=np.float64)))
    return sums


def _tweedie(observed: np.ndarray, variance: np.ndarray, where: np.ndarray, span: float = 400.0) -> np.ndarray:
    """E[true signal | observed], float64 (N,): Tweedie's formula ``x + var * d/dx log p(x)``.

    Binning noise variances by a noisy signal dilutes the slope: where most pixels are dark, those
    observed a little brighter are mostly dark ones with positive noise, so their bin's mean signal
    overstates their true one (and the lowest bin understates). The correction needs only the
    observed density ``p`` (of the pixels ``where``), here a histogram on 1 DN steps over the lowest
    ``span`` DN smoothed by
    2 DN; above that the noise is small against the signal's spread and nothing is changed.
    """
    lo = float(observed[where].min()) if where.any() else 0.0
    edges = np.arange(lo - 8.0, lo + span + 8.0, 1.0)
    counts, _ = np.histogram(observed[where], edges)
    kernel = np.exp(-0.5 * (np.arange(-6, 7) / 2.0) ** 2)
    density = np.convolve(counts.astype(np.float64), kernel / kernel.sum(), mode="same") + 1e-3
    centres = 0.5 * (edges[:-1] + edges[1:])
    score = np.gradient(np.log(density), centres)
    inside = observed < lo + span
    out = observed.astype(np.float64, copy=True)
    out[inside] += variance[inside] * np.interp(observed[inside], centres, score)
    return out


def triple_samples(first: np.ndarray, second: np.ndarray, third: np.ndarray, static: np.ndarray | None,
                   floor: float, high: float, model: tuple[float, float], max_samples: int = 100_000,
                   strata: int = 24) -> NoiseSamples:
    """Samples from three frames' signals (float (H, W), DN above black) at pixels static in all three.

    As :func:`temporal_samples`, but the pixels are grouped by the third frame's own value, whose
    noise is independent of the first two's: the grouping value is the pixel's own light, so the
    groups follow the signal more closely than its neighbours do where the scene has texture.
    Pixels are chosen by ``x3`` alone: dropped within four noise standard deviations of a clip level,
    and at most ``max_samples`` kept, spread over ``strata`` signal strata (equal steps of
    log(x3 + 2 DN), as the fit's bins): a stratum with fewer pixels than its share keeps them all and
    the others share the rest, each sampled evenly (:func:`_stratified`). A frame-wide stride would
    keep one pixel in ten or twenty everywhere, also in the dark strata of a bright scene, where the
    read noise shows and pixels are few. A choice by ``x3`` leaves the samples' expectations exact.
    """
    flat = [np.asarray(x).ravel() for x in (first, second, third)]
    mask = None if static is None else np.asarray(static, bool).ravel()
    sums = _static_sums(flat, mask)
    if min(sums) <= 0:
        return NoiseSamples(np.zeros(0), np.zeros(0))
    k, ratio = sums[0] / sums[1], sums[0] / sums[2]
    candidates, which = _clear_strata(flat[2], mask, ratio, floor, high, model, strata)
    chosen = _stratified(which, max_samples, strata)
    if chosen.size < 100:
        return NoiseSamples(np.zeros(0), np.zeros(0))
    idx = candidates[chosen]
    a, b, c = (flat[j][idx].astype(np.float64) for j in range(3))
    return _difference_samples(a, b, k, _grouped(0.5 * (a + k * b), c * ratio))


def _clear_strata(third: np.ndarray, mask: np.ndarray | None, ratio: float, floor: float, high: float,
                  model: tuple[float, float], strata: int, chunk: int = 1 << 18) -> tuple[np.ndarray, np.ndarray]:
    """The positions in ``third`` (float (N,) DN) that ``mask`` (bool (N,); None: all) holds and whose value times
    ``ratio`` is clear of clipping (:func:`_clear_of_clipping`), int32 (int64 beyond 2**31 pixels), and the signal
    stratum of each (uint8, :func:`_bin_index` over them). Readings of whole DN (no response curve) are looked up
    in a table of their values: the same result as computing it for every pixel, at a fraction of the cost.

    A live stream runs this beside the reconstruction of the next frames, so its whole-frame arrays add to the
    process's peak: whole-DN readings are read in passes of ``chunk`` pixels (their range, the codes present,
    then the positions and strata kept; the result does not depend on it), so that beside the two results only
    one chunk's temporaries are held (at 1920x1200 with every pixel static, 11 MiB at most instead of 37)."""
    spans = [(start, min(start + chunk, third.size)) for start in range(0, third.size, chunk)]

    def values_in(span: tuple[int, int]) -> np.ndarray:
        part = third[span[0]:span[1]]
        return part if mask is None else part[mask[span[0]:span[1]]]

    whole = _whole_range(values_in, spans)
    if whole is None:  # not whole DN: per pixel
        candidates = _positions(third.size, mask)
        c = third[candidates].astype(np.float64) * ratio
        keep = _clear_of_clipping(c, floor, high, model)
        which = _bin_index(c[keep], strata)[0] if keep.any() else np.zeros(0, np.int64)
        return candidates[keep], which.astype(np.uint8)
    lo, top, code_type = whole
    values = (np.arange(top + 1) + lo).astype(np.float64) * ratio
    clear = _clear_of_clipping(values, floor, high, model)

    def kept(span: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """The codes (value minus ``lo``) of the chunk's readings clear of clipping, and which readings they are."""
        code = values_in(span).astype(code_type)
        code -= lo
        keep = clear[code]
        return code[keep], keep

    seen = np.zeros(values.size, bool)
    count = 0
    for span in spans:
        code = kept(span)[0]
        seen[code] = True
        count += code.size
    present = np.flatnonzero(seen)
    table = np.zeros(values.size, np.uint8)
    if present.size:
        table[present] = _bin_index(values[present], strata)[0]
    candidates = outside_heap((count,), _position_type(third.size))  # (a run's, seldom: not kept in the heap)
    which = outside_heap((count,), np.uint8)
    at = 0
    for span in spans:
        code, keep = kept(span)
        positions = np.arange(*span, dtype=candidates.dtype)
        candidates[at:at + code.size] = (positions if mask is None else positions[mask[span[0]:span[1]]])[keep]
        which[at:at + code.size] = table[code]
        at += code.size
    return candidates, which


def _positions(size: int, mask: np.ndarray | None) -> np.ndarray:
    """The positions ``mask`` (bool (size,); None: all) holds, ascending: int32 where ``size`` allows, else intp."""
    positions = np.arange(size, dtype=_position_type(size))
    return positions if mask is None else positions[mask]


def _position_type(size: int) -> type:
    """The type of positions in an array of ``size`` elements: int32 where it holds them, else intp."""
    return np.int32 if size <= np.iinfo(np.int32).max else np.intp


def _whole_range(values_in: Callable[[tuple[int, int]], np.ndarray],
                 spans: list[tuple[int, int]]) -> tuple[int, int, type] | None:
    """Where every value of the chunks ``values_in(span)`` (float, DN), read twice, is a whole number and all of
    them span less than 2**20: (the smallest, the largest minus it, the integer type that holds them: int32, else
    int64), else None. (0, 0, int32) for no values."""
    ends = [(part.min(), part.max()) for part in map(values_in, spans) if part.size]
    lo, hi = (float(np.min([e[0] for e in ends])), float(np.max([e[1] for e in ends]))) if ends else (0.0, 0.0)
    if not hi - lo < 2**20:
        return None
    code_type = np.int64 if not (np.iinfo(np.int32).min < lo and hi < np.iinfo(np.int32).max) else np.int32
    top = 0
    for part in map(values_in, spans):
        code = part.astype(code_type)
        if not np.array_equal(code, part):
            return None
        if code.size:
            top = max(top, int(code.max()) - int(lo))
    return int(lo), top, code_type


def _stratified(which: np.ndarray, budget: int, strata: int, chunk: int = 1 << 16) -> np.ndarray:
    """At most ``budget`` positions of ``which`` (uint8 (N,), each position's stratum, < ``strata`` <= 255):
    the largest per-stratum quota whose total fits the budget, every stratum with fewer positions keeping
    them all; within a stratum every m-th position in order (its 0th, m-th, 2m-th, ...). int32 (M,) (int64
    beyond 2**31 positions, or when all are kept), ascending. Read ``chunk`` positions at a time (the result
    does not depend on it), so that nothing of N is made beside ``which``."""
    if which.size <= budget:
        return np.arange(which.size)
    chunks = range(0, which.size, chunk)
    # (np.bincount reads its input as intp: a chunk at a time, not a copy of N at 8 bytes a position)
    counts = sum(np.bincount(which[start:start + chunk], minlength=strata) for start in chunks)
    ordered = np.sort(counts)
    # water filling: the quota q with sum(min(counts, q)) <= budget
    below = np.concatenate([[0], np.cumsum(ordered)])[:-1]
    above = strata - np.arange(strata)
    j = int(np.count_nonzero(below + ordered * above <= budget))  # the j smallest strata keep all theirs
    quota = max((budget - int(below[j])) // int(above[j]), 1) if j < strata else int(ordered[-1])
    step = np.maximum(-(-counts // quota), 1)
    seen = np.zeros(counts.size, np.int64)  # each stratum's positions in the chunks before
    picks = []
    for start in chunks:
        part = which[start:start + chunk]
        local = np.argsort(part, kind="stable")  # the chunk's positions stratum by stratum, in order
        here = np.bincount(part, minlength=counts.size)
        first = np.cumsum(here) - here  # each stratum's first place in ``local``
        stratum = part[local]
        rank = seen[stratum] + np.arange(local.size) - first[stratum]  # each position's place in its stratum
        picks.append(local[rank % step[stratum] == 0] + start)
        seen += here
    return np.sort(np.concatenate(picks)).astype(_position_type(which.size))


def pair_fit(previous: np.ndarray, current: np.ndarray, sensor: Sensor, *, floor: float | None = None,
             static: np.ndarray | None = None, config: EstimatorConfig = EstimatorConfig(),
             max_samples: int = 4_000_000, period: tuple[int, int] | None = None
             ) -> tuple[NoiseSamples, LineFit | None]:
    """The noise line from two frames of a static scene (signals above black, float (H, W)).

    Iterated: the clip margins of :func:`temporal_samples` start from twice the default sensor's
    noise (generous) and then follow the fit. ``floor``: the lowest signal a reading can take
    (``-black`` for raw frames). ``period``: the frames' tile (rows, columns), when known: the pixels
    are grouped by neighbours of the same exposure and colour (:func:`temporal_samples`).
    """
    floor = -float(sensor.black_level) if floor is None else floor
    high = _high_level(sensor)
    model = (4.0 / (DEFAULT_FULL_WELL_E / sensor.range_dn),
             4.0 * ((DEFAULT_READ_NOISE_E * sensor.range_dn / DEFAULT_FULL_WELL_E) ** 2 + QUANTISATION_VARIANCE))
    fixed = _fixed(sensor)
    samples, fit = NoiseSamples(np.zeros(0), np.zeros(0)), None
    for _ in range(3):
        samples = temporal_samples(previous, current, static, floor, high, model, max_samples, period)
        fit = fit_line(*bin_samples(samples, config, temporal=True), **fixed,
                       outlier_tolerance=config.outlier_tolerance)
        if fit is None:
            break
        model = (fit.slope, fit.intercept)
    return samples, fit
