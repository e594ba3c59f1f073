"""The band refresh (issue 25): a live stream that runs ``adaptive`` only where its history needs a new estimate.

In a still view almost every pixel's history is settled (n = max_history: a new frame adds 1 / n of its
estimate). :class:`svelive.reconstruction.stream.Reconstructor` with ``refresh=K`` (monochrome frames, method
``adaptive``, temporal fusion, no within-frame test) then runs the method per frame on

- the bands (:data:`BAND_ROWS` rows) where something moved within the last max_history frames: more moving
  pixels in a frame than the false alarms of the test this stream shows make likely (:func:`moving_bands`: a
  quasi-Poisson test of the band's count against the median band's rate and the counts' spread, so a stream
  whose test flags many clustered false alarms, dim 1/1/8/8, settles as a quieter one does),
- the bands whose history is not settled (more than :data:`UNSETTLED_SHARE` of their pixels with
  n < max_history: a stream's start, a restart),
- a round-robin 1 / K of the settled bands (the history keeps refreshing and follows slow changes),
- every band when there is no history (a stream's first frame, after a reset or a restart) or the light changed
  in the frame before (fusion.illumination_ratio measured a ratio beyond fusion.RATIO_TOLERANCE, which it does
  only where the frame's differences from the history say so beyond their noise);

a pixel of a skipped band takes its history's mean (times the brightness ratio) as this frame's estimate
(:func:`svelive.reconstruction.fusion.fuse`'s ``predicted`` rows): its mean stays as it is, its own readings,
the test's window mean (made for every pixel, every frame: :func:`window_rows`) and its weight go on; a pixel
the test resets there gets this frame's estimate on demand (:func:`on_demand`: whole bands where they hold
many, else a patch atlas of :data:`CELL` px cells with their halos).

The method on a crop with a halo of :func:`halo_for` rows and columns (a multiple of the tile) gives the full
frame's results in the crop's interior, bit for bit, given the full frame's noise model (computed once per
frame): so do the bands and the atlas here.

Which bands run is decided by the history a frame is fused into: ``Reconstructor.estimate`` takes a hint from
the history the stream holds then, and ``Reconstructor.fuse`` computes the bands the hint missed
(:func:`method_on_band_rows`) and treats those it took beyond the selection as skipped, so frames estimated
ahead fuse as the sequential stream's, bit for bit. A colour stream (``colour_refresh``) runs it on its folded
luminance (a monochrome input of per-pixel exposures; its chroma and fold on every pixel). The live service runs
it for monochrome and colour streams (svelive.reconstruction.live.LIVE_REFRESH); the library's default is off.
"""

from __future__ import annotations

from concurrent.futures import Executor
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from svelive.core.pattern import Pattern
from svelive.jit import kernel
from svelive.memory import outside_heap
from svelive.reconstruction.fusion import COUNTED_STEP, SkippedResets, _running_mean
from svelive.reconstruction.methods.adaptive import _estimate, _shares_window
from svelive.reconstruction.methods.adaptive.fallback import Dark, _wide_reach
from svelive.reconstruction.methods.adaptive.parameters import kernels as method_kernels
from svelive.reconstruction.methods.base import (SveInput, map_on, reflect_101, thread_count, tile_rows,
                                                 window_kernels, window_level_row)
from svelive.reconstruction.numerics import (INLINE_TAPS, _kept_row_sums, _symmetric_column, _symmetric_row,
                                             _window_layout, _window_strip)

#: Rows of a band, the unit of the selection (adaptive's strips: 64 rows).
BAND_ROWS = 64
#: Rows and columns around a computed region that the method reads (its window, three deep, and the wide
#: fallback's blocks reach 13); a multiple of every tile's rows used here.
HALO = 16  # (for 3-tap windows, 2x2 tiles; longer windows take a multiple of it: halo_for)
#: The chance that a still band runs the method for the motion test's false alarms alone, per frame's selection
#: (:func:`moving_bands`; against the round-robin's 1 / K of the bands, K up to 64).
FALSE_SELECTION = 1e-3
#: The largest share of a band's pixels that :func:`moving_bands` takes as the stream's false alarms (the constant
#: share the selection used alone before; 2 to 10 times what still views show: 0.1 % on dim 1/1/8/8, 0.02-0.06 %
#: on the other patterns and levels): a view whose median band moves more than this is mostly moving, and its bands
#: are judged against this share with the least dispersion.
FALSE_ALARM_LIMIT = 0.002
#: A band more than this share of whose pixels are unsettled (n < max_history: a stream's start, a restart) runs
#: the method every frame.
UNSETTLED_SHARE = 0.3
#: Noise deviations beyond which a pixel the fusion reset where a reading in its window crossed the censor level
#: takes this frame's estimate in a skipped band (else it keeps its history): far looser than the fusion's test
#: (MotionConfig.temporal_sigmas), since such a window mean shifts beyond its noise (the still demo: 5 % of them
#: beyond 4 deviations); an object moving in seeds it, and the spread through the readings that crossed
#: (:func:`skipped_resets`) takes the rest (8, 16 and 32 pass the motion tests alike with bands skipped from
#: the second frame; the demo's demand: 1800, 1100, 800 pixels a frame).
UNSTABLE_SIGMAS = 16.0
#: Cells (px, square, aligned to the frame's grid) by which :func:`on_demand` counts a band's demand.
CELL = 16
#: The grid (px) on which :func:`on_demand` gathers the pixels it is asked for into boxes (8: a false alarm of the
#: motion test, widened, spans one or two such cells; a 16 px cell with 32-row halos cost 15 times its pixels).
GRAIN = 8
#: A band with at least this many on-demand cells is computed whole instead (a band with its halos costs
#: (BAND_ROWS + 2 HALO) W pixels, a cell (CELL + 2 HALO)^2).
CELL_LIMIT_SHARE = 0.6


@dataclass(eq=False)  # (by identity: the stream holds the frames in flight in a WeakSet)
class Partial:
    """A frame whose method ran on some bands only.

    Attributes:
        inp: the frame's prepared input; noise: its noise model (gain, read noise) as the method takes it.
        computed: bool (bands,), the bands whose rows hold the method's estimate (and the window mean completed
            with it); at :meth:`Reconstructor.estimate` a hint taken from the history the stream held then,
            made the stream's own selection by :meth:`Reconstructor.fuse`.
        rows: bool (H,), ``computed`` by row.
        hint: a weak reference (weakref.ref) to the history whose mean the skipped rows' window mean took where
            the window holds no uncensored reading (None: every band computed): weak, since a frame in flight
            holding it strongly kept a whole history (about 40 MB at 1920x1200) alive after the stream moved on,
            and :meth:`Reconstructor.fuse` only asks whether it is the history the frame is fused into.
        tick: the round-robin's turn the hint took (the partial frames fused and in flight when it was estimated).
        stats: counts for benchmarks (bands, computed, on-demand pixels and cells, bands the fuse added or
            dropped against the hint).
    """

    inp: SveInput
    noise: tuple[float, float]
    computed: np.ndarray
    rows: np.ndarray
    hint: object | None = None
    tick: int = 0
    stats: dict = field(default_factory=dict)


@lru_cache(maxsize=16)
def halo_for(pattern: Pattern) -> tuple[int, int]:
    """(rows, columns), each a multiple of :data:`HALO`, around a computed region that ``adaptive`` reads for this
    pattern's windows: its pass, three windows deep, then the wide fallback's widest blocks (fallback._wide_reach).
    (16, 16) for 3-tap windows (2x2 tiles); (32, 16) for the 5-row windows of 4-row tiles (1/1/8/8: 6 + 22 rows,
    3 + 13 columns), whose bands and cells with a halo of 16 rows differed from the full frame's in dim regions."""
    ky, kx = method_kernels(pattern.shape)
    reach = _wide_reach(ky, kx)
    need = 3 * (len(ky) // 2) + reach[0], 3 * (len(kx) // 2) + reach[1]
    return tuple(HALO * max(1, -(-n // HALO)) for n in need)


@lru_cache(maxsize=16)
def pass_halo(pattern: Pattern, period: tuple[int, int]) -> tuple[int, int]:
    """(rows, columns), each a multiple of the tile ``period``'s side (the input's: a crop starts on whole tiles),
    around a computed region that ``adaptive``'s pass reads, three windows deep, without the wide fallback's reach
    (:func:`halo_for`'s): enough for every pixel the fallback leaves as the pass made it, which :func:`on_demand`
    tells by the pass's own candidates. (4, 4) for 3-tap windows (2x2 tiles), (8, 4) for the 5-row windows of
    1/1/8/8."""
    ky, kx = method_kernels(pattern.shape)
    need = 3 * (len(ky) // 2), 3 * (len(kx) // 2)
    return tuple(n * max(1, -(-r // n)) for r, n in zip(need, period))


def bands(h: int) -> list[slice]:
    return [slice(top, min(top + BAND_ROWS, h)) for top in range(0, h, BAND_ROWS)]


def runs(flags: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) of the runs of True in a 1-d bool array."""
    padded = np.zeros(flags.size + 2, np.int8)
    padded[1:-1] = flags
    edges = np.flatnonzero(padded[1:] != padded[:-1]).tolist()  # (Python ints at once: x3-10 on 19-1200 flags)
    return list(zip(edges[::2], edges[1::2]))


def band_rows(flags: np.ndarray, h: int) -> list[tuple[int, int]]:
    """[start, stop) frame rows of the runs of True in ``flags`` (bool (bands,), one per :data:`BAND_ROWS` rows)
    of a frame of ``h`` rows."""
    return [(a * BAND_ROWS, min(b * BAND_ROWS, h)) for a, b in runs(flags)]


def band_counts(sampled: np.ndarray) -> np.ndarray:
    """int (bands,): the True values per band of ``sampled``, bool (ceil(H / 4), W), a frame's every 4th row
    (rows 0, 4, 8, ...: :data:`BAND_ROWS` / 4 of them a band; fusion.COUNTED_STEP), counted on a contiguous
    copy."""
    sampled = np.ascontiguousarray(sampled)
    q = BAND_ROWS // COUNTED_STEP
    return np.array([np.count_nonzero(sampled[k:k + q]) for k in range(0, sampled.shape[0], q)])


def band_sums(row_counts: np.ndarray) -> np.ndarray:
    """int (bands,): :func:`band_counts` of counts made per row, ``row_counts`` (int (H,): a frame row's count, read
    on its every fusion.COUNTED_STEP-th row alone)."""
    return np.add.reduceat(row_counts[::COUNTED_STEP], np.arange(0, -(-row_counts.shape[0] // COUNTED_STEP),
                                                                   BAND_ROWS // COUNTED_STEP))


def moving_bands(band_motion: list[np.ndarray], band_pixels: np.ndarray, cluster: int = 1,
                 false_selection: float = FALSE_SELECTION, limit: float = FALSE_ALARM_LIMIT) -> np.ndarray:
    """bool (bands,): the bands where something moved within the frames of ``band_motion`` (a list of F int
    (bands,) arrays: each frame's moving pixels per band on every 4th row, :func:`band_counts`) beyond the false
    alarms this stream's motion test shows. ``band_pixels``: int (bands,), the pixels each band's counts are of
    (its every 4th row). ``cluster``: the fewest sampled pixels one false alarm adds (2 widen + 1: a flag needs a
    flagged neighbour and is widened by ``widen``, so it covers at least that much of a sampled row).

    A still band's count is the pixels of false-alarm clusters: a Poisson number of clusters, each several pixels
    (adjacent pixels share the test's window readings, then the widening), so a compound Poisson count, of mean
    mu and variance D mu with D = E[S^2] / E[S] >= ``cluster`` (S: a cluster's pixels). It is tested as the
    quasi-Poisson count D Poisson(mu / D). The stream's own evidence gives mu and D, robust while fewer than half
    of the bands move: the false-alarm rate a pixel is the median over bands of their mean rate over the frames
    (most bands of a view are still; the mean over frames keeps it off 0 on streams with a cluster a band every
    few frames); D = (1.4826 MAD)^2 / mu, at least ``cluster``, with MAD the median absolute deviation of every
    band's and frame's count (scaled to a mean band): the variance it gives a normal spread, so D holds the
    clusters' sizes and the bands' different rates (a dim region makes more false alarms). A band moves when its
    largest count exceeds the quantile at 1 - ``false_selection`` / F of its quasi-Poisson count (one test a
    frame), or the one a rate of ``limit`` with D = ``cluster`` gives, if lower: when more than half of the bands
    move, the median is a moving band's and the stream's own rate is not the false alarms'; the limit still runs
    those bands. (A D thousands of times mu, a view split about evenly between still and moving bands, puts the
    quantile at 0: every band with a count runs.)
    """
    if not band_motion:
        return np.zeros(len(band_pixels), bool)
    counts = np.asarray(band_motion, np.float64)  # (F, bands)
    pixels = np.asarray(band_pixels, np.float64)
    rates = counts / pixels
    rate = float(np.median(rates.mean(axis=0)))
    typical = float(pixels.mean())
    spread = 1.4826 * float(np.median(np.abs(rates - np.median(rates)))) * typical
    dispersion = max(spread * spread / (rate * typical) if rate > 0 else 0.0, float(cluster))
    own, floor = poisson_quantile(np.concatenate((rate * pixels / dispersion, limit * pixels / cluster)),
                                  false_selection / counts.shape[0]).reshape(2, -1)
    return counts.max(axis=0) > np.minimum(dispersion * own, cluster * floor)


def poisson_quantile(mean: np.ndarray, p: float) -> np.ndarray:
    """int (n,): per element of ``mean`` (float (n,), >= 0), the least k with P(N > k) <= ``p`` for N Poisson of
    that mean (its pmf summed in logs, exact to float64)."""
    # (a frame's bands but its last have the same pixels: their means are one)
    values, inverse = np.unique(np.maximum(np.asarray(mean, np.float64), 1e-300), return_inverse=True)
    top = int(np.max(values + 12.0 * np.sqrt(values) + 40.0))  # (beyond: a tail far below any p asked)
    k = np.arange(top + 1)
    log_factorial = np.concatenate(([0.0], np.cumsum(np.log(np.arange(1, top + 1)))))
    pmf = np.exp(k * np.log(values)[:, None] - values[:, None] - log_factorial)
    within = 1.0 - np.cumsum(pmf, axis=1) <= p  # P(N > k) <= p
    return np.where(within.any(axis=1), np.argmax(within, axis=1), top)[inverse.ravel()]


def band_mask(flags: np.ndarray, h: int) -> np.ndarray:
    """bool (h,): ``flags`` (bool (bands,)) by frame row."""
    return np.repeat(flags, BAND_ROWS)[:h]


def method_on_bands(inp: SveInput, noise: tuple[float, float], selected: np.ndarray, image: np.ndarray,
                    lower: np.ndarray, variance: np.ndarray, window: np.ndarray | None,
                    workers: int | Executor = 1) -> None:
    """The method on the selected bands (bool per band), each run of them one crop with its halo, written into
    ``image``, ``lower``, ``variance`` and (with ``window``, (2, H, W)) the window mean: the rows of the selected
    bands hold their results; the halo rows of each crop (:func:`halo_for`), are overwritten too (with what the
    crop gives there), the other rows are left. A band between two runs is at least two halos (64 rows, halos of
    16 or 32): runs do not overwrite each other's results."""
    h = inp.shape[0]
    in_pass = window is not None and _shares_window(inp)
    halo = halo_for(inp.pattern)[0]
    for top, stop in band_rows(selected, h):
        rows = slice(max(top - halo, 0), min(stop + halo, h))
        _estimate(inp.crop(rows), noise, workers, want_variance=True, want_window=in_pass,
                  out=(image[rows], lower[rows], variance[rows], window[:, rows] if in_pass else None))


def _candidates(darks: list[Dark]) -> np.ndarray:
    """bool (rows, W): the wide fallback's candidates of adaptive's strips (``darks``, one below the other), where a
    strip without any holds no array of them (its weights give its rows)."""
    return np.concatenate([d.candidates if d.count else np.zeros(d.weights.shape, bool) for d in darks])


def method_on_band_rows(inp: SveInput, noise: tuple[float, float], selected: np.ndarray, image: np.ndarray,
                        lower: np.ndarray, variance: np.ndarray, workers: int | Executor = 1) -> None:
    """:func:`method_on_bands` (without the window mean) writing the selected bands' rows alone: each run of
    them one crop with its halo into arrays of its own, whose band rows are copied into ``image`` (float32
    (H, W), DN), ``lower`` (bool (H, W)) and ``variance`` (float32 (H, W), DN^2); every other row is left as it
    was (a band computed beside one the frame holds already: :meth:`Reconstructor.fuse` completing an estimate
    whose selection was a hint)."""
    h, w = inp.shape
    halo = halo_for(inp.pattern)[0]
    for top, stop in band_rows(selected, h):
        rows = slice(max(top - halo, 0), min(stop + halo, h))
        n = rows.stop - rows.start
        out = np.empty((n, w), np.float32), np.empty((n, w), bool), np.empty((n, w), np.float32)
        _estimate(inp.crop(rows), noise, workers, want_variance=True, out=(*out, None))
        core = slice(top - rows.start, stop - rows.start)
        for target, crop in zip((image, lower, variance), out):
            target[top:stop] = crop[core]


def window_rows(inp: SveInput, image: np.ndarray, variance: np.ndarray, rows: list[tuple[int, int]],
                level: np.ndarray, noise: np.ndarray, cache: dict | None = None,
                workers: int | Executor = 1) -> None:
    """The motion tests' window mean (numerics.window_estimate, bit-identical) of the frame rows ``rows``
    ([start, stop) pairs) into ``level`` and ``noise`` (float32 (H, W), DN and DN^2); ``image`` and ``variance``
    (float32 (H, W)) where the window holds no uncensored reading. Nominal tiles with inline windows only.
    ``cache``: a dict the caller keeps across a stream's frames for the tables of :func:`_clean_tables` (one
    entry), or None (made for this call). ``workers``: the rows are cut into pieces (:func:`pieces`) spread
    over these threads (methods.base.map_on); each row's result is made from its window's rows alone, so the
    results do not depend on it. A folded input (a colour frame's luminance: per-pixel exposures, which no
    table by row phase holds) takes numerics._window_strip, the generic pass of numerics.window_estimate."""
    if inp.folded or inp.pattern.pixel_map is not None:
        _window_rows_per_pixel(inp, image, variance, rows, level, noise, workers)
        return
    layout = _window_layout(inp.pattern, inp.period, inp.shape)
    kernels = layout.kernels
    if kernels[0].size > INLINE_TAPS[0] or kernels[1].size > INLINE_TAPS[1]:
        raise NotImplementedError("window_rows: windows longer than the inline taps")
    h, w = inp.shape
    period = min(inp.pattern.shape[0], h)
    sensor = inp.sensor
    inv_gain, floor = np.float32(1.0 / sensor.effective_gain), np.float32(sensor.floor_variance)
    exposure = inp.exposure[:period]
    row_tables, tables, row_of = _clean_tables(exposure, kernels, inp.pattern.shape[0], inp.period[0], h,
                                               {} if cache is None else cache)

    def strip(span: tuple[int, int]) -> None:
        _window_strip_clean(inp.signal, exposure, inp.censored, *span, *kernels, inv_gain, floor,
                            image, variance, level, noise, row_tables, tables, row_of)

    map_on(workers, strip, pieces(rows, thread_count(workers)))


def _window_rows_per_pixel(inp: SveInput, image: np.ndarray, variance: np.ndarray, rows: list[tuple[int, int]],
                           level: np.ndarray, noise: np.ndarray, workers: int | Executor = 1) -> None:
    """:func:`window_rows` of an input whose exposures are per pixel (float32 (H, W), a folded colour luminance):
    numerics._window_strip over each piece of ``rows``, the pass numerics.window_estimate runs on such an input
    (same kernels, same order of sums: bit-identical to its rows), with no tables (every window row's sums of e,
    G^2 e and G^2 are made again: they vary from pixel to pixel)."""
    kernels = window_kernels(inp.period)
    if kernels[0].size > INLINE_TAPS[0] or kernels[1].size > INLINE_TAPS[1]:
        raise NotImplementedError("window_rows: windows longer than the inline taps")
    sensor = inp.sensor
    inv_gain, floor = np.float32(1.0 / sensor.effective_gain), np.float32(sensor.floor_variance)
    no_rows = np.empty((4, 0, inp.shape[1]), np.float32)

    def strip(span: tuple[int, int]) -> None:
        _window_strip(inp.signal, inp.exposure, inp.censored, *span, *kernels, inv_gain, floor, image, variance,
                      level, noise, no_rows)

    map_on(workers, strip, pieces(rows, thread_count(workers)))


def pieces(rows: list[tuple[int, int]], threads: int, least: int = BAND_ROWS) -> list[tuple[int, int]]:
    """``rows`` ([start, stop) pairs) cut into about 4 ``threads`` pieces (the threads take them as they come free,
    so runs of unequal lengths still end about together) of at least ``least`` rows (a piece makes the row sums of
    its window's rows beyond it again), a run shorter than that whole; one thread: ``rows``."""
    total = sum(b - a for a, b in rows)
    if threads <= 1 or total < 2 * least:
        return list(rows)
    size = max(least, -(-total // (4 * threads)))
    out = []
    for a, b in rows:
        n = max(1, (b - a) // size)
        cuts = [a + (b - a) * k // n for k in range(n + 1)]
        out += list(zip(cuts[:-1], cuts[1:]))
    return out


def _clean_tables(exposure: np.ndarray, kernels, pattern_rows: int, window_rows: int, h: int, cache: dict):
    """(row_tables, tables, row_of) of :func:`_window_strip_clean` for a frame of ``h`` rows whose exposures repeat
    ``exposure`` ((P, W), row r's is row r % P): the sums along a row of e (``kernels[1]``), of e and of 1
    (``kernels[3]``) by row phase, (3, P, W); those sums down the window's rows (``kernels[0]``, ``kernels[2]``) of
    a frame without censored readings, (3, S, W), on the rows of numerics' small frame (methods.base.tile_rows),
    ``row_of`` (H,) mapping the frame's rows to them. Made with the kernels that sum the frame's windows (the same
    arithmetic, in the same order): kept in ``cache`` (one entry: a stream's frames share them), made again when
    the exposure rows, kernels or height change."""
    key = (exposure.tobytes(), exposure.shape, tuple(k.tobytes() for k in kernels), pattern_rows, window_rows, h)
    if key not in cache:
        a = kernels[0].size // 2
        small, row_of = tile_rows(h, int(np.lcm(window_rows, pattern_rows)), a)
        row_tables = np.empty((3, exposure.shape[0], exposure.shape[1]), np.float32)
        tables = np.empty((3, small, exposure.shape[1]), np.float32)
        _fill_tables(np.ascontiguousarray(exposure, np.float32), *kernels, row_tables, tables)
        row_of = row_of.astype(np.intp)
        for array in (row_tables, tables, row_of):
            array.setflags(write=False)
        cache.clear()  # (one stream's frames: one entry)
        cache[key] = (row_tables, tables, row_of)
    return cache[key]


@kernel
def _fill_tables(exposure, ky, kx, ky2, kx2, row_tables, tables):
    """:func:`_clean_tables`' arrays, into ``row_tables`` and ``tables``."""
    period, cols = exposure.shape
    ones = np.ones(cols, np.float32)
    e = np.empty(cols, np.float32)
    one = np.float32(1)
    for p in range(period):
        for c in range(cols):
            e[c] = exposure[p, c] * one  # (as the frame's kept exposures)
        _symmetric_row(e, kx, row_tables[0, p])
        _symmetric_row(e, kx2, row_tables[1, p])
        _symmetric_row(ones, kx2, row_tables[2, p])
    small = tables.shape[1]
    a = ky.size // 2
    phases = np.empty(ky.size, np.intp)
    for t in range(small):
        for j in range(ky.size):
            phases[j] = reflect_101(t - a + j, small) % period
        _symmetric_column(row_tables, 0, phases, ky, tables[0, t])
        _symmetric_column(row_tables, 1, phases, ky2, tables[1, t])
        _symmetric_column(row_tables, 2, phases, ky2, tables[2, t])


@kernel
def _column_mixed(ring, q, slots, clean, row_tables, phases, k, out):
    """numerics._symmetric_column of the window's rows, a row without censored readings (``clean`` by slot) read
    from ``row_tables[q - 1, phases[slot]]`` instead of the ring."""
    a = k.size // 2
    s = slots[a]
    centre = row_tables[q - 1, phases[s]] if clean[s] else ring[q, s]
    kc = k[a]
    for c in range(out.size):
        out[c] = centre[c] * kc
    for j in range(1, a + 1):
        s, t = slots[a - j], slots[a + j]
        above = row_tables[q - 1, phases[s]] if clean[s] else ring[q, s]
        below = row_tables[q - 1, phases[t]] if clean[t] else ring[q, t]
        kj = k[a + j]
        for c in range(out.size):
            out[c] = out[c] + (above[c] + below[c]) * kj


@kernel
def _window_strip_clean(signal, exposure, censored, first, stop, ky, kx, ky2, kx2, inv_gain, floor, image, variance,
                        out, out_var, row_tables, tables, row_of):
    """numerics._window_strip (without ``row_sums``) of rows ``first:stop``, bit for bit, where rows hold no censored
    reading: such a window row's sums of e, G^2 e and G^2 along it are its phase's ``row_tables`` row (only its sum
    of s is made), and an output row whose window rows all hold none takes those sums down its window from
    ``tables`` (row ``row_of[r]``); see :func:`_clean_tables`. The readings change every frame, so the sum of s is
    made for every pixel; the other three depend on the censoring alone."""
    rows, cols = signal.shape
    period = exposure.shape[0]
    size = ky.size
    a = size // 2
    one = np.float32(1)
    ring = np.empty((4, size, cols), np.float32)
    clean = np.zeros(size, np.bool_)
    phases = np.zeros(size, np.intp)
    kept, kept_signal, kept_exposure = (np.empty(cols, np.float32), np.empty(cols, np.float32),
                                        np.empty(cols, np.float32))
    sums = np.empty((4, cols), np.float32)
    slots = np.empty(size, np.intp)
    never = np.zeros(size, np.bool_)  # (the sums of s: always the ring's)
    following = first - a
    for r in range(first, stop):
        while following <= r + a:
            src = reflect_101(following, rows)
            slot = (following - first + a) % size
            following += 1
            e_row, s_row, c_row = exposure[src % period], signal[src], censored[src]
            n = 0
            for c in range(cols):
                n += c_row[c]
            phases[slot] = src % period
            clean[slot] = n == 0
            if n == 0:  # s * 1 is s: the kept signal is the row
                for c in range(cols):
                    kept_signal[c] = s_row[c] * one
                _symmetric_row(kept_signal, kx, ring[0, slot])
                continue
            _kept_row_sums(e_row, s_row, c_row, kx, kx2, kept, kept_signal, kept_exposure, ring, slot)
        whole = True
        for j in range(size):
            slots[j] = (r - a + j - first + a) % size
            whole = whole and clean[slots[j]]
        _column_mixed(ring, 0, slots, never, row_tables, phases, ky, sums[0])
        level_row, noise_row = out[r], out_var[r]
        if whole:
            t = row_of[r]
            lost = window_level_row(sums[0], tables[0, t], tables[1, t], tables[2, t], inv_gain, floor, level_row,
                                    noise_row)
        else:
            _column_mixed(ring, 1, slots, clean, row_tables, phases, ky, sums[1])
            _column_mixed(ring, 2, slots, clean, row_tables, phases, ky2, sums[2])
            _column_mixed(ring, 3, slots, clean, row_tables, phases, ky2, sums[3])
            lost = window_level_row(sums[0], sums[1], sums[2], sums[3], inv_gain, floor, level_row, noise_row)
        for c in range(cols if lost else 0):
            if np.isinf(noise_row[c]):
                level_row[c], noise_row[c] = image[r, c], variance[r, c]


def demand_boxes(shape: tuple[int, int], ys: np.ndarray, xs: np.ndarray, grain: tuple[int, int],
                 halo: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The boxes :func:`on_demand` computes for the pixels (``ys``, ``xs``, intp (n,)) of a frame of ``shape``:
    the pixels marked on a grid of ``grain`` (rows, cols) px, each group of grid cells that touch (8-connected)
    one box, its bounding rectangle, unless that rectangle with its ``halo`` (rows, cols) costs more pixels than
    its grid cells would each with theirs (a long thin group, a ring): then each of its grid cells is a box.
    Returns (boxes, box_of): int (m, 4) [r0, r1, c0, c1) frame rows and columns (starting on whole grid cells,
    clipped to the frame), and each pixel's box, intp (n,)."""
    import cv2

    h, w = shape
    gy, gx = grain
    hy, hx = halo
    grid = np.zeros((-(-h // gy), -(-w // gx)), np.uint8)
    cy, cx = ys // gy, xs // gx
    grid[cy, cx] = 1
    # (Grana's block-based labelling: the same labels and stats as the default (Spaghetti), a third of its time
    # on this sparse grid)
    n, labels, found, _ = cv2.connectedComponentsWithStatsWithAlgorithm(grid, 8, cv2.CV_32S, cv2.CCL_GRANA)
    x, y, bw, bh, cells = (found[1:, k].astype(np.intp) for k in range(5))  # (label 0: the grid's empty cells)
    whole = (bh * gy + 2 * hy) * (bw * gx + 2 * hx) <= cells * (gy + 2 * hy) * (gx + 2 * hx)
    label_of = labels[cy, cx].astype(np.intp) - 1
    if not whole.all():  # the grid cells of the groups split, each a box of its own after the whole groups'
        split = ~whole[label_of]
        marked, cell_of = np.unique(cy[split] * grid.shape[1] + cx[split], return_inverse=True)
        label_of[split] = np.count_nonzero(whole) + cell_of
        y, x = np.concatenate((y[whole], marked // grid.shape[1])), np.concatenate((x[whole], marked % grid.shape[1]))
        bh = np.concatenate((bh[whole], np.ones(marked.size, np.intp)))
        bw = np.concatenate((bw[whole], np.ones(marked.size, np.intp)))
        renumber = np.cumsum(whole) - 1
        label_of[~split] = renumber[label_of[~split]]
    boxes = np.stack([y * gy, np.minimum((y + bh) * gy, h), x * gx, np.minimum((x + bw) * gx, w)], axis=1)
    return boxes, label_of


def box_grain(pattern: Pattern) -> tuple[int, int]:
    """(rows, cols) px of :func:`demand_boxes`' grid for this pattern: :data:`GRAIN`, or the least multiple of it
    that holds whole tiles (a box then starts on whole tiles, as a crop must)."""
    return tuple(int(np.lcm(GRAIN, n)) for n in pattern.shape)


def _atlas(inp: SveInput, boxes: np.ndarray, halo: tuple[int, int] | None = None
           ) -> tuple[SveInput, np.ndarray, np.ndarray]:
    """The patches of ``boxes`` (int (n, 4) [r0, r1, c0, c1) of the frame, each inside the frame by ``halo``
    ((rows, cols); None: :func:`halo_for`'s), starting on whole tiles) with their halos, side by side in one row (a patch shorter
    than the row over zero readings); returns the atlas and each box's offset (atlas minus frame coordinates),
    rows and columns, intp (n,) each."""
    hy, hx = halo_for(inp.pattern) if halo is None else halo
    heights, widths = boxes[:, 1] - boxes[:, 0] + 2 * hy, boxes[:, 3] - boxes[:, 2] + 2 * hx
    shape = (int(heights.max()), int(widths.sum()))
    signal = np.zeros(shape, np.float32)
    censored = np.zeros(shape, bool)
    # every patch starts on whole tiles: the atlas's exposures are the pattern's, or a folded input's own per
    # pixel (copied with the patch; the pattern's in the atlas's empty slots)
    exposure = np.array(inp.pattern.exposure_map(shape), np.float32)
    per_pixel = inp.folded or inp.pattern.pixel_map is not None
    xs = np.concatenate(([0], np.cumsum(widths)[:-1]))
    fys, fxs = boxes[:, 0] - hy, boxes[:, 2] - hx
    for x, fy, fx, py, px in zip(xs.tolist(), fys.tolist(), fxs.tolist(), heights.tolist(), widths.tolist()):
        signal[:py, x:x + px] = inp.signal[fy:fy + py, fx:fx + px]
        censored[:py, x:x + px] = inp.censored[fy:fy + py, fx:fx + px]
        if per_pixel:
            exposure[:py, x:x + px] = inp.exposure[fy:fy + py, fx:fx + px]
    atlas = SveInput(signal, exposure, censored, inp.pattern, inp.sensor, inp.integral, folded=inp.folded)
    return atlas, -fys, xs - fxs


def _shelves(boxes: np.ndarray, halo: tuple[int, int]) -> list[np.ndarray]:
    """The atlases :func:`on_demand` makes of the interior ``boxes`` (int (n, 4)): indices into them, one
    :func:`_atlas` each, boxes of about the same height side by side, rows up to 2048 px (each method call on a
    few thousand pixels costs about as much again in its set-up)."""
    hy, hx = halo
    widths = boxes[:, 3] - boxes[:, 2] + 2 * hx
    order = np.argsort(boxes[:, 1] - boxes[:, 0], kind="stable")
    shelves, current, used = [], [], 0
    for k in order.tolist():
        if current and used + widths[k] > 2048:
            shelves.append(np.array(current, np.intp))
            current, used = [], 0
        current.append(k)
        used += int(widths[k])
    shelves.append(np.array(current, np.intp))
    return shelves


def on_demand(part: Partial, ys: np.ndarray, xs: np.ndarray, workers: int | Executor = 1, narrow: bool = True
              ) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray], dict]:
    """This frame's estimate at the pixels (``ys``, ``xs``, intp), in rows the method skipped: (ys, xs), their
    (image, lower, variance), and counts (pixels, bands computed whole, cells of CELL px, boxes, the pixels
    the method ran on for the boxes, halos included, and the boxes' pixels the wide fallback took).

    A band holding so many such pixels' cells (CELL px) that the band costs less whole is computed whole; the
    other pixels are gathered into boxes (:func:`demand_boxes`: the pixels that lie together, on a grid of
    :func:`box_grain`), each computed with its halo: interior boxes in atlases (their patches side by side, one row
    each), boxes at the frame's edges in a stack per side. ``narrow``: the halo of the method's pass first
    (:func:`pass_halo`), then the pixels among them that the wide fallback takes (the pass's candidates, whose result
    reads beyond that halo) again in boxes with :func:`halo_for`'s (about a quarter of the pixels on the still demo;
    where most pixels are candidates, a dim view, the first boxes are lost work); else :func:`halo_for`'s at once.
    The results do not depend on it. The atlases and stacks run on the caller's thread (a few small calls of the
    method, mostly Python and small numpy steps: spread over a pool, the two threads took turns at the GIL and
    the call took more wall and CPU time than on one, still demo); the bands computed whole run the method on
    ``workers``."""
    inp, noise = part.inp, part.noise
    h, w = inp.shape
    n = ys.size
    stats = dict(demand_px=int(n), demand_bands=0, demand_cells=0, demand_boxes=0, demand_area=0, demand_wide=0)
    values = (np.empty(n, np.float32), np.empty(n, bool), np.empty(n, np.float32))
    if not n:
        return ys, xs, values, stats
    cw = -(-w // CELL)
    cell_of = (ys // CELL) * cw + xs // CELL
    cells, inverse = np.unique(cell_of, return_inverse=True)
    band_of_cell = ((cells // cw) * CELL) // BAND_ROWS
    hy, hx = halo_for(inp.pattern)
    py, px = pass_halo(inp.pattern, inp.period) if narrow else (hy, hx)  # (a cell's cost)
    limit = CELL_LIMIT_SHARE * (BAND_ROWS + 2 * hy) * w / ((CELL + 2 * py) * (CELL + 2 * px))
    whole = np.zeros(len(part.computed), bool)
    counts = np.bincount(band_of_cell, minlength=len(whole))
    whole[:] = counts >= limit
    in_whole = whole[band_of_cell]
    stats["demand_bands"] = int(np.count_nonzero(whole))
    stats["demand_cells"] = int(np.count_nonzero(~in_whole))

    def take(pixels: np.ndarray, arrays, oy, ox) -> None:
        """values at ``pixels`` (indices into ys, xs) from result arrays at (ys + oy, xs + ox)."""
        y, x = ys[pixels] + oy, xs[pixels] + ox
        for value, array in zip(values, arrays):
            value[pixels] = array[y, x]

    if whole.any():
        # (whole frames of which a few bands are written and read: pages of their own, handed back when they go,
        # not 21 MB more on malloc's heap that the process keeps at its peak)
        image, lower, variance = (outside_heap((h, w), np.float32), outside_heap((h, w), bool),
                                  outside_heap((h, w), np.float32))
        method_on_bands(inp, noise, whole, image, lower, variance, None, workers)
        take(np.nonzero(in_whole[inverse])[0], (image, lower, variance), 0, 0)
    rest = np.nonzero(~in_whole[inverse])[0]
    if narrow:  # the boxes with the pass's halo; the pixels the wide fallback takes (it reads farther) again
        wide = _boxes_on_demand(inp, noise, ys, xs, rest, pass_halo(inp.pattern, inp.period), take, stats)
        if wide.size:
            _boxes_on_demand(inp, noise, ys, xs, wide, (hy, hx), take, stats)
    else:
        wide = _boxes_on_demand(inp, noise, ys, xs, rest, (hy, hx), take, stats)
    stats["demand_wide"] = int(wide.size)
    return ys, xs, values, stats


def _boxes_on_demand(inp: SveInput, noise: tuple[float, float], ys: np.ndarray, xs: np.ndarray, pixels: np.ndarray,
                     halo: tuple[int, int], take, stats: dict) -> np.ndarray:
    """:func:`on_demand` of its pixels ``pixels`` (indices into ``ys``, ``xs``) by boxes (:func:`demand_boxes`), each
    with ``halo`` (rows, cols): interior boxes in atlases, boxes at the frame's edges in a stack per side, each one
    call of the method on the caller's thread; their values given to ``take(pixels, arrays, oy,
    ox)``. Returns the pixels among ``pixels`` that the wide fallback takes (the pass's candidates, intp): with
    :func:`pass_halo`'s halo, exact for the others alone (they need :func:`halo_for`'s)."""
    h, w = inp.shape
    hy, hx = halo
    if not pixels.size:
        return pixels
    boxes, box_of = demand_boxes((h, w), ys[pixels], xs[pixels], box_grain(inp.pattern), halo)
    stats["demand_boxes"] += len(boxes)
    # (a patch's results do not depend on its neighbours in an atlas: its halo is the method's reach)
    inside = (boxes[:, 0] - hy >= 0) & (boxes[:, 1] + hy <= h) & (boxes[:, 2] - hx >= 0) & (boxes[:, 3] + hx <= w)
    interior = np.nonzero(inside)[0]
    jobs = []
    if interior.size:
        jobs = [(interior[m], lambda m: _atlas(inp, boxes[m], halo))
                for m in _shelves(boxes[interior], halo)]
    edge = np.nonzero(~inside)[0]
    for members in _edge_groups(inp.shape, boxes[edge], halo):
        jobs.append((edge[members], lambda m: _edge_stack(inp, boxes[m], halo)))

    def solve(job) -> tuple:
        members, build = job
        box, oy, ox = build(members)
        image, lower, variance, _, darks, _ = _estimate(box, noise, 1, want_variance=True)
        candidates = _candidates(darks) if any(d.count for d in darks) else None
        return (image, lower, variance), candidates, oy, ox, box.shape[0] * box.shape[1]

    slot = np.empty(len(boxes), np.intp)
    again = []
    for (members, _), (arrays, candidates, oy, ox, area) in zip(jobs, map(solve, jobs)):
        slot[:] = -1
        slot[members] = np.arange(members.size)
        s = slot[box_of]
        mine = np.nonzero(s >= 0)[0]
        oy, ox = oy[s[mine]], ox[s[mine]]
        take(pixels[mine], arrays, oy, ox)
        if candidates is not None:
            again.append(pixels[mine][candidates[ys[pixels[mine]] + oy, xs[pixels[mine]] + ox]])
        stats["demand_area"] += area
    return np.concatenate(again) if again else pixels[:0]


def _edge_groups(shape: tuple[int, int], boxes: np.ndarray, halo: tuple[int, int] = (HALO, HALO)
                 ) -> list[np.ndarray]:
    """:func:`on_demand`'s boxes whose halo crosses the frame's edge (``boxes``: int (n, 4) [r0, r1, c0, c1)),
    grouped by the side they cross (top, bottom, left, right, in that order of precedence), along it in order,
    each group one :func:`_edge_stack`: indices into ``boxes``. A box clipped at the start (end) of its side
    (the left or top end) opens (closes) a group, so that its clipped edge is the stack's, mirrored as the
    frame's; a box clipped on both sides across its own (a frame shorter than it with its halos) is a group of
    its own."""
    h, w = shape
    hy, hx = halo
    clipped = np.stack([boxes[:, 0] - hy < 0, boxes[:, 1] + hy > h, boxes[:, 2] - hx < 0, boxes[:, 3] + hx > w], 1)
    side = np.where(clipped[:, 0], 0, np.where(clipped[:, 1], 1, np.where(clipped[:, 2], 2, 3)))
    groups = []
    for s in range(4):
        along = s < 2  # top and bottom boxes side by side along the rows, left and right ones one under the other
        members = np.nonzero(side == s)[0]
        members = members[np.lexsort((boxes[members, 0], boxes[members, 2]) if along
                                     else (boxes[members, 2], boxes[members, 0]))]
        start, end = (2, 3) if along else (0, 1)
        across = (0, 1) if along else (2, 3)
        current: list[int] = []
        for k in members.tolist():
            if clipped[k, across[0]] and clipped[k, across[1]]:
                groups.append(np.array([k], np.intp))
                continue
            if current and (clipped[k, start] or clipped[current[-1], end]):
                groups.append(np.array(current, np.intp))
                current = []
            current.append(k)
        if current:
            groups.append(np.array(current, np.intp))
    return groups


def _edge_stack(inp: SveInput, boxes: np.ndarray, halo: tuple[int, int] | None = None
                ) -> tuple[SveInput, np.ndarray, np.ndarray]:
    """The boxes of one group of :func:`_edge_groups` (``boxes``: int (n, 4) [r0, r1, c0, c1)), each with its halo
    (``halo``, (rows, cols); None: :func:`halo_for`'s) clipped to the frame, stacked along their side into one input (top and bottom ones side by side in the given
    order, left and right ones one under the other), each box's clipped side on the stack's edge (mirrored as the
    frame's), boxes that abut meeting at their halos. Returns the stack and each box's offsets (stack minus frame
    coordinates), intp (n,) each."""
    h, w = inp.shape
    hy, hx = halo_for(inp.pattern) if halo is None else halo
    first = boxes[0]
    top, bottom, left = first[0] - hy < 0, first[1] + hy > h, first[2] - hx < 0
    along = top or bottom  # side by side along the rows, else one under the other
    spans = [(max(r0 - hy, 0), min(r1 + hy, h), max(c0 - hx, 0), min(c1 + hx, w)) for r0, r1, c0, c1 in boxes.tolist()]
    across = max((b[1] - b[0]) if along else (b[3] - b[2]) for b in spans)
    total = sum((b[3] - b[2]) if along else (b[1] - b[0]) for b in spans)
    shape = (across, total) if along else (total, across)
    # a bottom (right) box shorter across than the others sits at the stack's far edge; above (left of) it
    # zero readings with the pattern's exposures, beyond its halo
    signal, censored = np.zeros(shape, np.float32), np.zeros(shape, bool)
    exposure = np.array(inp.pattern.exposure_map(shape), np.float32)
    oy, ox, offset = [], [], 0
    for r0, r1, c0, c1 in spans:
        if along:
            y, x = (0 if top else across - (r1 - r0)), offset
            offset += c1 - c0
        else:
            y, x = offset, (0 if left else across - (c1 - c0))
            offset += r1 - r0
        signal[y:y + r1 - r0, x:x + c1 - c0] = inp.signal[r0:r1, c0:c1]
        censored[y:y + r1 - r0, x:x + c1 - c0] = inp.censored[r0:r1, c0:c1]
        exposure[y:y + r1 - r0, x:x + c1 - c0] = inp.exposure[r0:r1, c0:c1]
        oy.append(y - r0)
        ox.append(x - c0)
    stack = SveInput(signal, exposure, censored, inp.pattern, inp.sensor, inp.integral, folded=inp.folded)
    return stack, np.array(oy, np.intp), np.array(ox, np.intp)


def skipped_resets(found: SkippedResets, skipped: np.ndarray, reset: np.ndarray, new_censored: np.ndarray,
                   old_censored: np.ndarray, old_test: np.ndarray, tested: np.ndarray, scale: np.float32, wy: int,
                   wx: int, weight: np.ndarray, test: np.ndarray, censored: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, int, np.ndarray]:
    """The pixels the fusion reset in the frame rows the method skipped (``skipped``, bool (H,)) that take this
    frame's estimate on demand, the others keeping their history as it was: the fusion's pass judged each by itself
    (fusion._skipped_row: ``found``, and the kept pixels' history written into the new state), and here, since a
    history is made of windows whose readings kept their censoring, where a reading that crossed the censor level
    lies in the window (``wy``, ``wx`` either side) of a pixel taking this frame (on demand, or reset outside the
    skipped rows), every pixel whose window holds it takes it too, and so on: such a pixel gets back what the
    fusion gave a reset pixel (weight 1, the test's estimate its running mean with weight 1 of the history's
    ``old_test`` and the frame's ``tested``, times ``scale``, the frame's censoring ``new_censored``) in
    ``weight``, ``test`` (of no rows where the test has no history of its own) and ``censored`` (the new state's);
    its own readings and mean are the on-demand estimate's, which the caller writes. ``reset``: bool (H, W), the
    fusion's; ``old_censored``: bool (H, W), the history's censoring. Float arrays float32 (H, W).

    Returns (ys, xs, kept, given): the on-demand pixels' coordinates, intp (n,), in reverse raster order; how many
    kept their history; the flat indices (intp, ascending) of the pixels the fusion's pass let keep their history
    that take weight 1 back here (among ``ys``, ``xs``). Each pixel's outcome is a closure that does not depend on
    the order of the pixels (nor on the fusion's strips)."""
    h, w = reset.shape
    # the stack starts with the listed pixels and the reset ones of the rows within 2 wy of a skipped row, and takes
    # each kept pixel (marked 1) at most once more: arrays of that size, not of the frame's (four maps a frame)
    kept = int(found.counts[:, 1].sum())
    rows = np.arange(h)
    skipped_before = np.concatenate(([0], np.cumsum(skipped)))
    near = skipped_before[np.minimum(rows + 2 * wy + 1, h)] > skipped_before[np.maximum(rows - 2 * wy, 0)]
    first = int(found.counts[:, 0].sum()) + int(np.count_nonzero(near & ~skipped)) * w
    stack_y, stack_x = np.empty(first + kept, np.intp), np.empty(first + kept, np.intp)
    taken_y, taken_x = np.empty(kept, np.intp), np.empty(kept, np.intp)
    spread = _spread_censoring(skipped, reset, new_censored, old_censored, wy, wx, found.mark, found.ys, found.xs,
                               found.starts, found.counts, stack_y, stack_x, old_test, tested, scale, weight, test,
                               censored, taken_y, taken_x)
    listed = [found.ys[a:a + n] * w + found.xs[a:a + n] for a, n in zip(found.starts, found.counts[:, 0])]
    given = np.sort(taken_y[:spread] * w + taken_x[:spread])
    flat = -np.sort(-np.concatenate([*listed, given]))  # reverse raster order
    ys, xs = np.divmod(flat, w)
    return ys, xs, kept - spread, given


@kernel
def _spread_censoring(skipped, reset, new_censored, old_censored, wy, wx, mark, ys, xs, starts, counts, stack_y,
                      stack_x, old_test, tested, scale, weight, test, censored, taken_y, taken_x):
    """:func:`skipped_resets`' spread through crossed readings, over the whole frame: from the pixels taking this
    frame (each strip's ``counts[k, 0]`` listed from ``ys[starts[k]]``, ``xs[...]``, and the pixels reset in rows
    that were not skipped but lie within 2 ``wy`` rows of one; on the stack, ``stack_y``, ``stack_x``), every pixel
    marked 1 whose window holds a reading that crossed the censor level in such a pixel's window is marked 2, given
    back a reset pixel's weight, test and censoring, and listed into ``taken_y``, ``taken_x`` (returned: how many),
    and so on. A reading visited gets 8 added to its mark."""
    h, w = mark.shape
    top = 0
    for k in range(starts.size):
        for i in range(counts[k, 0]):
            stack_y[top], stack_x[top] = ys[starts[k] + i], xs[starts[k] + i]
            top += 1
    for r in range(h):
        if skipped[r]:
            continue
        near = False
        for rr in range(max(r - 2 * wy, 0), min(r + 2 * wy + 1, h)):
            near = near or skipped[rr]
        if not near:
            continue
        for c in range(w):
            if reset[r, c]:
                stack_y[top], stack_x[top] = r, c
                top += 1
    separate = test.shape[0] > 0
    one = np.float32(1)
    taken = 0
    while top > 0:
        top -= 1
        r, c = stack_y[top], stack_x[top]
        for qr in range(max(r - wy, 0), min(r + wy + 1, h)):
            for qc in range(max(c - wx, 0), min(c + wx + 1, w)):
                if new_censored[qr, qc] == old_censored[qr, qc] or mark[qr, qc] >= 8:
                    continue
                mark[qr, qc] += 8  # (a reading visited)
                for yr in range(max(qr - wy, 0), min(qr + wy + 1, h)):
                    for yc in range(max(qc - wx, 0), min(qc + wx + 1, w)):
                        if mark[yr, yc] % 8 == 1:
                            mark[yr, yc] += 1
                            stack_y[top], stack_x[top] = yr, yc
                            top += 1
                            taken_y[taken], taken_x[taken] = yr, yc
                            taken += 1
                            weight[yr, yc] = one
                            if separate:
                                test[yr, yc] = _running_mean(old_test[yr, yc], tested[yr, yc], one, scale)
                            censored[yr, yc] = new_censored[yr, yc]
    return taken


def supports_colour(pattern: Pattern, cfa_shape: tuple[int, int], cell: tuple[int, int]) -> bool:
    """Whether a colour stream (joint, the luminance folded with the cells' shares) can skip bands of its luminance
    (prototype, issue 25): :func:`supports` of its exposure pattern, a colour filter tile and chroma cells
    (``cell``, rows x cols) whose sides divide :data:`CELL`, :data:`HALO` and :data:`BAND_ROWS` (a band, crop or
    patch starts on whole joint tiles and whole cell rows)."""
    sides = all(CELL % n == 0 and HALO % n == 0 and BAND_ROWS % n == 0 for n in (*cfa_shape, *cell))
    return sides and supports(pattern)


def supports(pattern: Pattern) -> bool:
    """Whether a monochrome stream of this exposure pattern can skip bands: a nominal tile (no per-pixel map)
    whose sides divide :data:`CELL`, :data:`HALO` and :data:`BAND_ROWS` (every band, crop and patch starts on
    whole tiles) and whose motion window :func:`window_rows` makes inline."""
    if pattern.pixel_map is not None:
        return False
    sides = all(CELL % n == 0 and HALO % n == 0 and BAND_ROWS % n == 0 for n in pattern.shape)
    k = window_kernels(pattern.shape)
    return sides and k[0].size <= INLINE_TAPS[0] and k[1].size <= INLINE_TAPS[1]
