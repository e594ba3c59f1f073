"""Motion-safe temporal fusion: a per-pixel history that resets where the scene moves.

Both tests ask the same question of the Poisson-Gaussian noise model
(sensor.py): do two estimates of one pixel's radiance differ by more than
their noise allows, ``(a - b)^2 > k^2 (var_a + var_b)``? Where they do, the
scene moved, and the pixel falls back to the information that is right for a
moving scene.

- Within a frame (``integration`` exposure timing, where long exposures
  integrate over a longer time than short ones): the frame's estimate is
  compared with the interpolation of the shortest exposure's uncensored
  samples alone; flagged pixels, widened by ``widen`` pixels, take the
  shortest exposure's estimate, which integrates over the shortest time.
- Across frames: a per-pixel recursive average (equal weights over the last
  ``max_history`` frames at most) fuses the frame estimates where the scene
  is static; a pixel whose new tested estimate (a window mean computed beside
  the method, svelive.reconstruction.numerics.window_estimate, with a history of
  its own) disagrees with its history is reset to the new estimate at once, so
  moving objects leave no trail; when most of the frame differs a little, the
  camera moved and every pixel is reset. Global brightness changes (lights
  switched, mains flicker) are first divided out with a robust global ratio, so
  they do not reset every pixel. Where a pixel has history, the output moves
  towards its fused own readings as far as the local evidence of detail allows.

Units: radiance in DN at relative exposure 1, variances in DN^2 at exposure 1.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import Executor
from dataclasses import dataclass
from functools import cached_property
from typing import NamedTuple

import numpy as np

from svelive.core.order import median
from svelive.jit import flat, kernel
from svelive.memory import outside_heap
from svelive.reconstruction.methods.base import (binomial_kernel, map_on, reflect_101, smooth, support_size,
                                                 thread_count)
from svelive.reconstruction.config import MotionConfig
from svelive.reconstruction.consistency import Inconsistency
from svelive.reconstruction.numerics import INLINE_TAPS, _maximum, _strips, _symmetric_row


@dataclass(frozen=True)
class TemporalState:
    """The per-pixel history of one stream. Arrays are never modified after creation.

    Attributes:
        mean: float32 (H, W), fused radiance, DN at exposure 1.
        own: float32 (H, W), fused radiance of each pixel's own readings (s / e;
            the frame's estimate where the reading was censored).
        weight: float32 (H, W), 1 / n with n = min(frames since the pixel's last
            reset, max_history): the weight its last frame had, and the variance
            of its mean over one frame's variance (conservative once n is capped).
        bound: bool (H, W), the mean is only a lower bound (all samples censored).
        censored: bool (H, W), the last frame's censored readings.
        test: float32 (H, W), the fused estimate the temporal test compares frames with
            (:attr:`FrameEstimate.test`), or None when that is ``mean``.
        own_variance: float32 (H, W), the running mean (weights as ``mean``'s) of each frame's own
            reading's variance at its estimate, where frames give a share error (colour frames, whose
            exposures e' = e k change with the shares from frame to frame: a reading over a share that
            was small in one frame, beside a moving object's colour, is that much noisier); None else
            (the exposures are fixed, and the current frame's tables give the variance).
    """

    mean: np.ndarray
    own: np.ndarray
    weight: np.ndarray
    bound: np.ndarray
    censored: np.ndarray
    test: np.ndarray | None = None
    own_variance: np.ndarray | None = None

    @property
    def tested(self) -> np.ndarray:
        """float32 (H, W), the fused estimate the temporal test compares frames with."""
        return self.mean if self.test is None else self.test


class ShareError(NamedTuple):
    """:attr:`FrameEstimate.share_error` by cell: pixel (r, c) has ``cells[channels[r % cy, c % cx], r // cy,
    c // cx]``.

    Attributes:
        cells: float32 (n, Hc, Wc), each plane's value per cell (a colour frame's: per channel).
        channels: uint8 (cy, cx), the plane of each pixel of a cell.
    """

    cells: np.ndarray
    channels: np.ndarray

    def plane(self, shape: tuple[int, int]) -> np.ndarray:
        """float32 ``shape`` (H, W): each pixel's value, the plane :attr:`FrameEstimate.share_error` may take
        instead."""
        out = np.empty(shape, np.float32)
        _share_gather(self.cells, self.channels, out)
        return out


@kernel
def _share_gather(cells, channels, out):
    """out (H, W) = ``cells`` (n, Hc, Wc) of each pixel's plane (``channels``: a cell's, (cy, cx)) and cell."""
    for r in range(out.shape[0]):
        _share_row(cells, channels, r, out[r])


@kernel(inline="always")
def _share_row(cells, channels, g, row):
    """row (W,) = frame row ``g`` of a :class:`ShareError` (``cells``, ``channels``)."""
    cy, cx = channels.shape
    w = row.size
    i, phase = g // cy, channels[g % cy]
    start = 0
    if cx == 2:  # cells of two columns spelt out: one loop writing both, that vectorises
        left, right, start = cells[phase[0], i], cells[phase[1], i], w // 2
        for j in range(start):
            row[2 * j] = left[j]
            row[2 * j + 1] = right[j]
    for t in range(cx):
        plane = cells[phase[t], i]
        for j in range(start, (w - t + cx - 1) // cx):
            row[j * cx + t] = plane[j]


@dataclass(frozen=True)
class FrameEstimate:
    """What one frame contributes to the history.

    Attributes:
        image, variance: float32 (H, W), the single-frame estimate (DN) and its variance (DN^2).
        bound: bool (H, W), ``image`` is only a lower bound there.
        censored: bool (H, W), readings at or above the censor level.
        signal: float32 (H, W), the readings s (DN above black).
        inverse: float32 (P, W), 1 / e by row phase: pixel (r, c) has ``inverse[r % P, c]``
            (P: the tile's rows, or H for a per-pixel exposure map). Rows rather than a
            whole map, so that the per-pixel pass reads a few rows that stay in cache. None
            with ``exposure`` instead.
        own_slope, own_floor: float32 (P, W), by row phase likewise, the variance of one frame's
            own reading, ``own_slope * L + own_floor`` at radiance L (1 / (e g) and sigma^2 / e^2),
            which the detail step compares the fused own readings' differences with; or, with
            ``exposure``, two numbers a and b standing for the tables ``a / e`` and ``b / e^2``
            (float32: (1 / e) * a and (1 / e) * (1 / e) * b), which the kernels then compute
            instead of reading them (a per-pixel exposure map's tables are whole frames).
        test, test_variance: float32 (H, W), the estimate the temporal test compares with the
            history, and its noise variance (DN, DN^2): a window mean whose loss of resolution
            is the same in every frame of a static scene
            (svelive.reconstruction.numerics.window_estimate), so that the test does not depend
            on how sharp the method's ``image`` is. None: ``image`` and ``variance`` themselves.
        share_error: float32 (H, W), the relative variance of an error of each pixel's own reading
            that frames do not average, or the same by cell (:class:`ShareError`: no plane written
            and read), or None (none: a monochrome frame). A colour frame's own
            reading is s / (e k), k its cell's share of its channel, which colour within the cells
            moves: the detail step's variance of the fused own reading is then its noise's plus
            ``share_error`` times the fused value squared, so that it does not sharpen towards that bias.
            Given only with per-pixel exposures (``exposure``);
            the fused own readings' noise variance is then tracked in the history
            (:attr:`TemporalState.own_variance`), since e' changes with the shares from frame to frame.
        exposure: float32 (H, W), each pixel's own exposure e (a colour frame's e' = e k, which no tile
            repeats and which changes from frame to frame), with ``own_slope`` and ``own_floor`` numbers
            and no ``inverse``: the kernels take 1 / e as they read it (bit-identical to a plane of
            1 / e, which is then neither written nor read: a frame's 4 bytes a pixel each way). None else.
    """

    image: np.ndarray
    variance: np.ndarray
    bound: np.ndarray
    censored: np.ndarray
    signal: np.ndarray
    inverse: np.ndarray | None
    own_slope: np.ndarray | float
    own_floor: np.ndarray | float
    test: np.ndarray | None = None
    test_variance: np.ndarray | None = None
    share_error: np.ndarray | ShareError | None = None
    exposure: np.ndarray | None = None

    def __post_init__(self) -> None:
        if (self.exposure is None) != (self.inverse is not None and np.ndim(self.own_slope) > 0):
            raise ValueError("FrameEstimate: row-phase tables (inverse, own_slope, own_floor arrays) or per-pixel "
                             "exposures (exposure, own_slope and own_floor numbers, no inverse)")

    @property
    def tested(self) -> tuple[np.ndarray, np.ndarray]:
        """(estimate, variance) the temporal test compares with the history."""
        return (self.image, self.variance) if self.test is None else (self.test, self.test_variance)

    @cached_property
    def own(self) -> np.ndarray:
        """float32 (H, W), each pixel's own reading s / e (``image`` where censored), computed on first use."""
        own = np.empty(self.image.shape, np.float32)
        per_pixel = self.exposure is not None
        _own_rows(self.signal, self.exposure if per_pixel else self.inverse, per_pixel, self.censored, self.image,
                  own)
        return own


@kernel
def _own_reading(signal, inverse, censored, image):
    """A pixel's own reading s / e, or the frame's estimate where the reading is censored."""
    return image if censored else signal * inverse


@kernel(inline="always")
def _inverse_at(exposures, p, c, per_pixel):
    """1 / e of pixel (row phase ``p``, column ``c``): ``exposures[p, c]`` holds it (a table of 1 / e by row
    phase), or holds e itself where ``per_pixel`` (:attr:`FrameEstimate.exposure`)."""
    return np.float32(1) / exposures[p, c] if per_pixel else exposures[p, c]


@kernel
def _own_rows(signal, exposures, per_pixel, censored, image, out):
    """out = own readings, (H, W) arrays with ``exposures`` by row phase (P, W): 1 / e, or e where
    ``per_pixel`` (:func:`_inverse_at`)."""
    period = exposures.shape[0]
    for r in range(out.shape[0]):
        p = r % period
        for c in range(out.shape[1]):
            out[r, c] = _own_reading(signal[r, c], _inverse_at(exposures, p, c, per_pixel), censored[r, c],
                                     image[r, c])


@dataclass(frozen=True)
class OutputVariance:
    """The variance of a fused output, computed when called (float32 (H, W), DN^2).

    The frame's variance times the weight of its frame in each pixel's mean,
    ``weight`` (the history's variance for a static scene with stationary noise;
    None: the frame's as it is), and the shortest exposure's where the within-frame
    test's finding ``replaced`` was applied: where it flagged, and also ``within``
    unless that is None. A whole-frame array the live path never reads: computing
    it on demand saves writing it (and the shortest exposure's variance).
    """

    frame: np.ndarray
    weight: np.ndarray | None = None
    replaced: Inconsistency | None = None
    within: np.ndarray | None = None

    def __call__(self) -> np.ndarray:
        variance = self.frame
        if self.weight is not None:
            variance = np.empty(self.frame.shape, np.float32)
            np.multiply(self.frame, self.weight, out=variance)
        if self.replaced is not None:
            used = self.replaced.flagged if self.within is None else self.replaced.flagged & self.within
            variance = np.where(used, self.replaced.variance, variance)
        return variance


@dataclass(frozen=True)
class Fused:
    """One frame's output of :func:`fuse`.

    Attributes:
        image: float32 (H, W), the output radiance.
        motion: bool (H, W), pixels whose history was reset because the scene moved
            (widened), or that the within-frame test flagged.
        history: float32 (H, W), 1 / n, n = frames in each pixel's mean (min(frames since reset, max_history)).
        illumination_ratio: the global brightness ratio divided out (frame / history).
        state: the history to pass with the next frame.
        variance_of: the output's variance, on demand; ``variance`` calls it on first access.
        reset: bool (H, W), pixels that took this frame's values without their history: ``motion``,
            and also where the test flagged a pixel alone, a reading crossed the censor level or
            either side is a lower bound; everywhere on a restart. Its complement holds the pixels
            the tests found still, the only ones whose frame differences are noise alone.
        skipped: what the pass found of the pixels it reset in the rows the method skipped (:func:`fuse`'s
            ``predicted``), or None (no such rows, or a restart).
        noise: a colour stream's evidence of its luminance noise after this frame and its floor
            (:class:`LuminanceNoise`, :func:`fuse`'s ``noise`` updated), made in the pass from its weights (``history``
            as the pass left it); None where not asked for, or on a restart.
        row_counts: int64 (H, 2), made in the pass: in its rows of frame rows that are multiples of
            :data:`COUNTED_STEP` (the others not written), the row's pixels of ``motion`` and its pixels of
            ``history`` (as the pass left it) above 1 / max_history; None on a restart or with a within-frame test.
    """

    image: np.ndarray
    motion: np.ndarray
    history: np.ndarray
    illumination_ratio: float
    state: TemporalState
    variance_of: OutputVariance
    reset: np.ndarray
    skipped: SkippedResets | None = None
    noise: LuminanceNoise | None = None
    row_counts: np.ndarray | None = None

    @cached_property
    def variance(self) -> np.ndarray:
        """float32 (H, W), the output's variance (:class:`OutputVariance`)."""
        return self.variance_of()


class LuminanceNoise(NamedTuple):
    """A colour stream's evidence of its luminance noise (svelive.reconstruction.stream.luminance_noise), which
    :func:`fuse`'s pass updates.

    Attributes:
        spread: float32 (H, W), DN^2, per pixel: the last frame's evidence, updated in place (:func:`noise_evidence`);
            0 where the history's weight is 1 (as the pass leaves it).
        floor: float32 (Hc, W), DN^2, per cell row and column: the mean of ``spread`` over the pixels of the column's
            cell whose weight is below 1 (:func:`cell_means`), updated in place.
        cell: (cy, cx), the cells' rows and columns.
        kept: bool, ``floor`` holds the last frame's, of ``spread`` and the history's weights as they are: a cell row
            whose weights are each below 1 where they were (so its evidence stays as it was) then keeps its row,
            which is what it would be made again, bit for bit; else every row is made.
    """

    spread: np.ndarray
    floor: np.ndarray
    cell: tuple[int, int]
    kept: bool


@dataclass(frozen=True)
class SkippedResets:
    """The pixels :func:`fuse` reset in the rows the method skipped (``predicted``), as its pass judged them
    (:func:`_skipped_row`): those that keep their history hold it already in the new state (weight, own readings,
    tested estimate, censoring); those that take this frame's estimate are listed, for the caller to compute
    (svelive.reconstruction.settle.skipped_resets, which also spreads the taking through crossed readings).

    Attributes:
        mark: int8 (H, W), 1 where a reset pixel of a skipped row keeps its history, 2 where it takes this frame's
            estimate, 0 elsewhere (every row written).
        ys, xs: intp (H W,), frame coordinates of the pixels marked 2: strip k's ``counts[k, 0]`` of them from
            ``starts[k]`` on, each strip's in raster order.
        starts: intp (strips,); counts: int64 (strips, 2), the pixels each strip marked 2 and 1.
    """

    mark: np.ndarray
    ys: np.ndarray
    xs: np.ndarray
    starts: np.ndarray
    counts: np.ndarray


#: :func:`illumination_ratio`'s step by default (a multiple of camera_moved's, whose pass it can share).
_RATIO_STEP = 8


def illumination_ratio(state: TemporalState, image: np.ndarray, variance: np.ndarray, bound: np.ndarray,
                       step: int = _RATIO_STEP, workers: int | Executor = 1) -> float:
    """Robust global brightness ratio frame / history: the median of image / the history's tested
    estimate (:attr:`TemporalState.tested`) over well-measured pixels; ``image`` and ``variance``
    are the frame's tested estimate (:attr:`FrameEstimate.tested`).

    Subsampled every ``step`` pixels; pixels count when both values are at least
    3 noise standard deviations (the frame's) above 0 and neither is a lower bound. Returns 1
    when fewer than 64 pixels qualify, and when nothing says the light changed: the mean of the
    differences image - history over every subsampled pixel that is not a bound, each clipped to
    :data:`RATIO_CLIP` standard deviations of the difference (v (1 + w): the frame's variance and the
    history's weight), is within :data:`RATIO_SIGMAS` of the standard error the noise model gives it
    (sqrt(sum v (1 + w)) / n: the differences' own spread, where the light changed, holds the scene's
    texture and would hide the change in a small frame) of 0. Where the light did not
    change each difference is frame noise minus history noise, of mean 0 whichever pixels are taken; the
    clip bounds what a moving object adds and leaves noise as it is. Neither the ratios' median (of pixels
    chosen because they read 3 deviations above 0, it leans towards those whose noise was positive) nor
    the differences' median (a dim frame's estimate is skewed, its history, a mean of several, less so)
    is 0 for noise: on still dim 1/1/8/8 frames the ratios' median read 0.1-0.7 % above 1, beyond
    :data:`RATIO_TOLERANCE` in most frames, their histories were scaled by it and drifted above the
    frames, and in a band refresh every band ran the method. ``workers``: pieces of rows spread over
    threads (map_on); the values are gathered in row order, so the result does not depend on it.
    """
    return _illumination(state, image, variance, bound, step, workers)[0]


def _illumination(state: TemporalState, image: np.ndarray, variance: np.ndarray, bound: np.ndarray, step: int,
                  workers: int | Executor, moved: tuple[FrameEstimate, MotionConfig] | None = None
                  ) -> tuple[float, bool | None]:
    """(:func:`illumination_ratio`, :func:`camera_moved` of ``moved`` (frame, config) at a ratio of 1 with its
    default step, or None without ``moved``): one pass over the subsample's rows, which the two share (the ratio's
    every ``step``-th, a multiple of camera_moved's step, among them), reading them from memory once."""
    h, w = image.shape
    across = -(-w // step)
    size = -(-h // step) * across
    ratios, differences = np.empty(size, np.float32), np.empty(size, np.float32)
    if moved is not None:
        frame, config = moved
        moved_step = _MOVED_STEP
        assert step % moved_step == 0
        inv_s2 = _moved_settings(config)

    def piece(rows: slice) -> tuple[np.ndarray, np.ndarray, float, np.ndarray | None]:
        at = rows.start // step * across
        arrays = (image[rows], state.tested[rows], variance[rows], bound[rows], state.bound[rows],
                  state.weight[rows], step, ratios[at:], differences[at:])
        if moved is None:
            count, unbound, noise = _subsampled_ratios(*arrays)
            counts = None
        else:
            counts = np.zeros(2, np.int64)
            count, unbound, noise = _subsampled_both(*arrays, frame.censored[rows], state.censored[rows], inv_s2,
                                                     moved_step, counts)
        return ratios[at:at + count], differences[at:at + unbound], noise, counts

    found = map_on(workers, piece, _subsample_pieces(h, step, workers))
    verdict = None if moved is None else _moved_verdict(np.sum([c for *_, c in found], axis=0), config)
    if sum(r.size for r, *_ in found) < 64:
        return 1.0, verdict
    changes = np.concatenate([d for _, d, *_ in found])
    # (the noise's standard error, the model's: a real change's spread, which follows the scene, is not noise)
    standard_error = np.sqrt(sum(v for _, _, v, _ in found)) / changes.size
    if abs(float(np.mean(changes, dtype=np.float64))) <= RATIO_SIGMAS * standard_error:
        return 1.0, verdict
    ratio = float(median(np.concatenate([r for r, *_ in found])))
    return (ratio if np.isfinite(ratio) and ratio > 0 else 1.0), verdict


def _subsample_pieces(h: int, step: int, workers: int | Executor) -> list[slice]:
    """The rows 0..h cut into a piece per thread of ``workers`` (map_on's), each starting on a row of every
    ``step``-th (the subsample's rows are the frame's)."""
    threads = thread_count(workers)
    sampled = -(-h // step)
    cuts = [sampled * k // threads * step for k in range(threads)] + [h]
    return [slice(a, b) for a, b in zip(cuts[:-1], cuts[1:]) if b > a]


@kernel
def _subsampled_ratios(image, mean, variance, bound, old_bound, weight, step, out, differences):
    """Writes image / mean of the well-measured pixels of every ``step``-th row and column
    (row-major) to ``out``, and image - mean, clipped to RATIO_CLIP standard deviations (variance (1 +
    weight)), of those of them that are not a bound to ``differences``; returns the two counts and the
    sum of those differences' variances (float64; the lost windows' infinite variances left out)."""
    count = unbound = 0
    noise = 0.0
    for i in range(0, image.shape[0], step):
        count, unbound, noise = _ratios_row(i, image, mean, variance, bound, old_bound, weight, step, out,
                                            differences, count, unbound, noise)
    return count, unbound, noise


@kernel
def _subsampled_both(image, mean, variance, bound, old_bound, weight, step, out, differences, censored,
                     old_censored, inv_s2, moved_step, counts):
    """:func:`_subsampled_ratios`, and :func:`_subsampled_exceeding`'s ``counts`` at a scale of 1 and every
    ``moved_step``-th row and column (a divisor of ``step``; ``image``, ``mean``: the tested estimates), each row
    read once for both."""
    count = unbound = 0
    noise = 0.0
    for i in range(0, image.shape[0], moved_step):
        _exceeding_row(i, image, mean, weight, variance, bound, old_bound, censored, old_censored, np.float32(1),
                       inv_s2, moved_step, counts)
        if i % step == 0:
            count, unbound, noise = _ratios_row(i, image, mean, variance, bound, old_bound, weight, step, out,
                                                differences, count, unbound, noise)
    return count, unbound, noise


@kernel(inline="always")
def _ratios_row(i, image, mean, variance, bound, old_bound, weight, step, out, differences, count, unbound, noise):
    """:func:`_subsampled_ratios` of row ``i``, its counts and sum so far given and returned."""
    nine, clip2 = np.float32(9), np.float32(RATIO_CLIP * RATIO_CLIP)
    for j in range(0, image.shape[1], step):
        if bound[i, j] or old_bound[i, j]:
            continue
        a, b, v = image[i, j], mean[i, j], variance[i, j]
        spread = v * (np.float32(1) + weight[i, j])
        limit = np.sqrt(clip2 * spread)
        differences[unbound] = min(max(a - b, -limit), limit)
        unbound += 1
        if spread < np.inf:
            noise += spread
        if a * a > nine * v and b * b > nine * v:
            out[count] = a / b
            count += 1
    return count, unbound, noise


#: :func:`camera_moved`'s step by default.
_MOVED_STEP = 4


def camera_moved(state: TemporalState, frame: FrameEstimate, scale: float, config: MotionConfig,
                 step: int = _MOVED_STEP, workers: int | Executor = 1) -> bool:
    """Did most of the frame change, each pixel perhaps below the per-pixel test's threshold?

    True when more than ``config.global_motion`` of the measured pixels of a subsample (every
    ``step``-th row and column; a pixel counts when neither the frame nor the history is a
    lower bound there and its reading kept its censoring) differ from the history (times
    ``scale``, the brightness ratio) by more than ``config.global_sigmas`` noise standard
    deviations, ``(x - mean)^2 > s^2 v (1 + w)`` on the tested estimates. A pan over smooth
    texture changes every pixel a little: the per-pixel test at k = 4 flags only part of
    it, and the rest would average with history from another place. False when fewer than
    64 pixels are measured. ``workers``: pieces of rows spread over threads (map_on), their counts summed.
    """
    tested, variance = frame.tested
    scale, inv_s2 = np.float32(scale), _moved_settings(config)

    def piece(rows: slice) -> np.ndarray:
        counts = np.zeros(2, np.int64)
        _subsampled_exceeding(tested[rows], state.tested[rows], state.weight[rows], variance[rows], frame.bound[rows],
                              state.bound[rows], frame.censored[rows], state.censored[rows], scale, inv_s2, step,
                              counts)
        return counts

    return _moved_verdict(np.sum(map_on(workers, piece, _subsample_pieces(tested.shape[0], step, workers)), axis=0),
                          config)


def _moved_settings(config: MotionConfig) -> np.float32:
    """:func:`camera_moved`'s 1 / s^2."""
    return np.float32(1.0 / config.global_sigmas ** 2)


def _moved_verdict(counts: np.ndarray, config: MotionConfig) -> bool:
    """:func:`camera_moved` of its counts [measured, exceeding] (:func:`_subsampled_exceeding`)."""
    measured, exceeding = (int(n) for n in counts)
    return measured >= 64 and exceeding > config.global_motion * measured


@kernel
def _subsampled_exceeding(image, mean, weight, variance, bound, old_bound, censored, old_censored, scale, inv_s2,
                          step, counts):
    """counts = [measured pixels, those beyond the threshold] of every ``step``-th row and column."""
    for i in range(0, image.shape[0], step):
        _exceeding_row(i, image, mean, weight, variance, bound, old_bound, censored, old_censored, scale, inv_s2,
                       step, counts)


@kernel(inline="always")
def _exceeding_row(i, image, mean, weight, variance, bound, old_bound, censored, old_censored, scale, inv_s2, step,
                   counts):
    """:func:`_subsampled_exceeding` of row ``i``, added to ``counts``."""
    one = np.float32(1)
    for j in range(0, image.shape[1], step):
        if bound[i, j] or old_bound[i, j] or censored[i, j] != old_censored[i, j]:
            continue
        d = image[i, j] - mean[i, j] * scale
        counts[0] += 1
        counts[1] += d * d * inv_s2 > (weight[i, j] + one) * variance[i, j]


#: The row-phase tables of :func:`_update_row` when it computes them (:class:`FrameEstimate`).
_NO_TABLE = np.empty((0, 0), np.float32)
_NO_TABLE.setflags(write=False)

#: :class:`_Frame`'s share error without one, and the cells of a share error given as a plane (H, W): one plane
#: of cells of 1 x 1 px.
_ONE_PLANE = np.zeros((1, 1), np.uint8)
_NO_SHARES = ShareError(np.empty((0, 0, 0), np.float32), _ONE_PLANE)
for _array in _NO_SHARES:
    _array.setflags(write=False)

#: The pass counts the moving and the unsettled pixels (weight above 1 / max_history) of every ``COUNTED_STEP``-th
#: frame row (rows 0, 4, 8, ...: :attr:`Fused.row_counts`), the rows by which the band refresh judges its bands
#: (svelive.reconstruction.settle.band_counts).
COUNTED_STEP = 4
#: :class:`_Outputs`' counts without them (a restart's, or with a within-frame test, which flags more after the pass).
_NO_COUNTS = np.empty((0, 2), np.int64)

#: An output of no rows (:class:`_Outputs`' own variance without one): never written, but writable, as the
#: arrays it stands for are.
_NO_ROWS = np.empty((0, 0), np.float32)

#: The row sums' kernel when the detail step's window is OpenCV's: a single tap of 1, read-only as
#: binomial kernels are (a kernel's compiled signature tells the two apart).
_ONE_TAP = np.ones(1, np.float32)
_ONE_TAP.setflags(write=False)

#: Rows per strip of :func:`fuse`. Its pass keeps each row's arrays in cache from the test to the
#: update whatever the strip's height (:func:`_fuse_strip`); taller strips test fewer halo rows
#: twice and make fewer calls (128 against 64: x0.94-0.95 CPU mono, x0.98 RGGB, demo 1920x1200).
FUSE_ROWS = 128

#: Global brightness ratios closer to 1 than this are not divided out.
RATIO_TOLERANCE = 2e-3
#: The light changed between history and frame only where the frame's differences from the history lean one way by
#: more than this many standard errors (:func:`illumination_ratio`): noise passes it in about one frame in 1.7
#: million (one or two a day at 30 fps).
RATIO_SIGMAS = 5.0
#: Standard deviations at which a pixel's difference from its history is clipped in that test (noise hardly reaches
#: it; a moving object's pixels add no more than it each).
RATIO_CLIP = 6.0


def start(frame: FrameEstimate) -> TemporalState:
    """A history holding one frame."""
    return TemporalState(frame.image, frame.own, np.ones(frame.image.shape, np.float32), frame.bound, frame.censored,
                         frame.test, None if frame.share_error is None else own_variance(frame))


def own_variance(frame: FrameEstimate) -> np.ndarray:
    """float32 (H, W), the variance of each pixel's own reading at the frame's estimate (a frame without
    row-phase tables, its per-pixel exposures: :class:`FrameEstimate`), as :func:`_update_row` computes it."""
    out = np.empty(frame.image.shape, np.float32)
    _own_variance_rows(frame.image, frame.exposure, np.float32(frame.own_slope), np.float32(frame.own_floor), out)
    return out


@kernel
def _own_variance_rows(image, exposure, slope_scale, floor_scale, out):
    one = np.float32(1)
    for r in range(out.shape[0]):
        for c in range(out.shape[1]):
            out[r, c] = _own_reading_variance(one / exposure[r, c], image[r, c], slope_scale, floor_scale)


@kernel(inline="always")
def _own_reading_variance(inverse, estimate, slope_scale, floor_scale):
    """The variance of a pixel's own reading (1 / e = ``inverse``) at ``estimate``, float32: shot noise at
    the estimate (not below 0) and the floor, both scaled as the frame's per-pixel numbers say."""
    return inverse * slope_scale * _maximum(estimate, np.float32(0)) + inverse * inverse * floor_scale


def fuse(state: TemporalState | None, frame: FrameEstimate, config: MotionConfig, pattern_shape: tuple[int, int],
         inconsistency: Inconsistency | None = None, detail: bool = True, workers: int = 1,
         strip_rows: int = FUSE_ROWS, executor: Executor | None = None,
         predicted: list[tuple[int, int]] | None = None,
         complete: Callable[[], FrameEstimate] | None = None,
         unstable_sigmas: float | None = None, noise: LuminanceNoise | None = None) -> Fused:
    """Fuse one frame into the per-pixel history.

    Args:
        state: the history, or None to start one (also when the frame size changed).
        frame: this frame's estimates; its arrays are not modified.
        pattern_shape: the exposure tile's shape (rows, cols).
        inconsistency: the within-frame test's finding, or None; applied to the
            output where the history is reset (everywhere on a stream's first
            frame), never to the history, which keeps estimates of one kind so
            that static texture, where the test also fires, keeps fusing.
        detail: where a pixel has history (2 frames or more), move the output towards
            its own fused readings as far as they exceed their noise (:func:`sharpen`
            at ``config.detail_sigmas``).
        workers: threads over which the strips are spread (the kernels and OpenCV
            release the GIL); the result does not depend on it.
        strip_rows: rows per strip; the result does not depend on it either.
        executor: a pool of ``workers`` threads the caller keeps across frames
            (svelive.reconstruction.methods.base.map_on); None: one is made for this call.
        predicted: rows ([start, stop) pairs) the method skipped (the band refresh, svelive.reconstruction.settle):
            their estimate is taken as the history's mean times the brightness ratio (so the mean stays,
            exactly) and their lower bound as the history's, written into ``frame.image`` (not where the
            ratio is 1 and a whole strip is skipped: its rows are then left unwritten) and ``frame.bound``
            here. With them, ``unstable_sigmas`` (svelive.reconstruction.settle.UNSTABLE_SIGMAS) is needed. A pixel
            the test resets there keeps its history (weight, own readings, tested estimate and
            the censoring it was made of, times the ratio) where it did not move, neither side is a lower
            bound, its window holds an uncensored reading and the tested estimates differ by at most
            ``unstable_sigmas`` noise deviations, with no brightness correction (:func:`_skipped_row`: reset
            only because a reading in its window crossed the censor level); the others are listed
            (:attr:`Fused.skipped`) for the caller to give their estimate
            (svelive.reconstruction.settle.skipped_resets). Needs ``complete``: called before any restart
            (every pixel then takes the frame's own estimate), it returns the frame with every row estimated.
        noise: a colour stream's evidence of its luminance noise (:class:`LuminanceNoise`; its ``spread`` the
            last frame's, zeros where there is none yet), or None: the pass updates ``spread`` in place
            (:func:`noise_evidence`; in ``predicted`` rows it stays, 0 where the new weight is 1) and ``floor``
            of the new weights, while the row's estimate, history and weights are in cache (:attr:`Fused.noise`).
            Its cells' rows must divide ``strip_rows``. On a restart both may be written in part.

    With w = 1 / n the history's weight state, a pixel is reset to the frame's
    estimate where the noise test ``(x - mean)^2 > k^2 v (1 + w)`` flags it (x, v: the
    frame's tested estimate and its variance, ``frame.test`` where given, and mean its
    fused history, held beside the fused ``image``),
    where either the history or the frame is only a
    lower bound (a bound cannot be averaged), and within a tile window of a
    reading that crossed the censor level. Flagged pixels count as motion when
    a neighbour is flagged too (every estimate spreads over a window, so does
    any real change; isolated flags are mostly noise); motion is widened by
    ``config.widen`` and reset too. When more than ``config.global_motion`` of
    the frame moves, or of a subsample differs beyond ``config.global_sigmas``
    (:func:`camera_moved`, tested first), the camera moved: every pixel is reset.
    Elsewhere it takes the running mean with weight 1 / min(n + 1, max_history).
    The history's variance is taken as the frame's variance v times w, as for a
    static scene with stationary noise. The test compares smooth estimates
    (``frame.test``: window means, whatever the method), whose loss of resolution
    is the same in every frame of a static scene and so cancels.

    Work is done in strips of ``strip_rows`` rows, each in one pass down its rows
    (:func:`_fuse_strip`: every row tested, then updated and sharpened a few rows
    later, while what the next step reads is in cache), reading a halo of rows
    around the strip for the neighbourhood operations, so strips join without a
    seam; the rows whose detail window crosses a join are sharpened once the strip
    beyond is in. Once the moving pixels found exceed ``config.global_motion`` of
    the frame, the frame restarts whatever the other strips hold, so they are
    skipped. The within-frame test of a strip's rows (``inconsistency``, computed
    on demand) runs just before its pass. The global brightness ratio is measured
    first, on a subsample.
    """
    image, variance, bound = frame.image, frame.variance, frame.bound
    if (state is None or state.mean.shape != image.shape or (state.test is None) != (frame.test is None)
            or (state.own_variance is None) != (frame.share_error is None)):
        if predicted:
            frame = complete()
        return _restart(frame, inconsistency, 1.0, np.zeros(image.shape, bool))
    if predicted:  # the skipped rows' bound is the history's (before anything reads it)
        for a, b in predicted:
            bound[a:b] = state.bound[a:b]
    tested, tested_variance = frame.tested
    history = state.tested
    threads = executor if executor is not None else workers
    # the ratio's pass also tells whether the camera moved, where the ratio is then 1 (most frames): its
    # subsample's rows read once (x0.85-0.87 CPU for the two passes, from memory; 1920x1200 demo, mono and RGGB)
    ratio, moved = (_illumination(state, tested, tested_variance, bound, _RATIO_STEP, threads, (frame, config))
                    if config.compensate_illumination else (1.0, None))
    # mean * 1 is exact: one kernel with and without a brightness correction
    scale = np.float32(ratio) if abs(ratio - 1.0) > RATIO_TOLERANCE else np.float32(1)
    if scale != 1 or moved is None:
        # (on this thread: a subsample's pass, 0.6 ms; spread over the pool it took more wall and CPU time)
        moved = camera_moved(state, frame, scale, config)
    if moved:
        if predicted:
            frame = complete()
        return _restart(frame, inconsistency, ratio, np.ones(image.shape, bool))
    h = image.shape[0]
    # the skipped rows' estimate: the history's mean times the ratio (the running mean then keeps it, bit for
    # bit: ``_running_mean`` of mean * scale and itself). With no brightness correction (mean * 1 is the mean),
    # a strip whose rows are all skipped reads the history's mean rows as the frame's instead (no pass writing
    # them into ``frame.image``, whose rows there are then left unwritten); the others' are written as it goes
    same = scale == 1
    kept = np.zeros(h, bool)
    for a, b in predicted or ():
        kept[a:b] = True
        if not same:
            np.multiply(state.mean[a:b], scale, out=image[a:b])
    strips = _strips(h, strip_rows)
    # the skipped rows' resets, judged in the pass (the new history's censoring a copy then: kept pixels keep theirs)
    if predicted:
        found = SkippedResets(np.empty(image.shape, np.int8), outside_heap(image.size, np.intp),
                              outside_heap(image.size, np.intp),
                              np.array([s.start * image.shape[1] for s in strips], np.intp),
                              np.zeros((len(strips), 2), np.int64))
        new_censored, unstable_k2 = np.empty_like(frame.censored), np.float32(1.0 / unstable_sigmas ** 2)
    else:
        found, new_censored, unstable_k2 = None, frame.censored, np.float32(0)
    strip_index = {s.start: k for k, s in enumerate(strips)}
    window = tuple(support_size(n) for n in pattern_shape)
    # rows a strip's motion mask depends on: censor changes grow by window // 2, then
    # confirmation looks 1 row further, widening ``widen`` more
    halo = window[0] // 2 + 1 + int(config.widen)
    inv_k2 = np.float32(1.0 / config.temporal_sigmas ** 2)
    motion = np.empty(image.shape, bool)
    reset = np.empty(image.shape, bool)
    # (a within-frame test flags more pixels as moving after the pass: none counted then)
    row_counts = np.empty((h, 2), np.int64) if inconsistency is None else None

    fused, own, weight = np.empty_like(image), np.empty_like(image), np.empty_like(image)
    own_var = None if state.own_variance is None else np.empty_like(image)
    separate = frame.test is not None  # the test's estimate has a history of its own
    fused_test = np.empty_like(image) if separate else fused
    # the output differs from the history's mean where sharpened or replaced by the within-frame test
    out = np.empty_like(image) if detail or inconsistency is not None else fused
    floor_weight = np.float32(1.0 / config.max_history)
    # with detail: each pixel's squared difference own - fused over its variance, whose window
    # mean is the local evidence of detail (once the rows of the window are fused); summed along
    # rows in the update where the detail step sums the columns itself. Written only where the
    # detail step of the rows around the strips' joins reads it (the strips' pass keeps a ring): so in
    # pages of its own, of which only those rows' are ever touched (a few %), not a frame's worth of heap
    evidence = outside_heap(image.shape, image.dtype) if detail else image
    ky, kx = (binomial_kernel(n) for n in window)
    radius = ky.size // 2
    inline = ky.size <= INLINE_TAPS[0] and kx.size <= INLINE_TAPS[1]
    along = kx if inline else _ONE_TAP
    # the shortest exposure's estimate, kept from the test of a strip to the detail pass
    shortest = np.empty_like(image) if detail and inconsistency is not None else None

    share = (_NO_SHARES if frame.share_error is None else frame.share_error
             if isinstance(frame.share_error, ShareError) else ShareError(frame.share_error[None], _ONE_PLANE))
    if frame.exposure is not None:  # the tables' scales: the kernel computes them from 1 / e
        tables = _Tables(frame.exposure, _NO_TABLE, _NO_TABLE, np.float32(frame.own_slope), np.float32(frame.own_floor))
    else:
        tables = _Tables(frame.inverse, frame.own_slope, frame.own_floor, np.float32(0), np.float32(0))

    threshold = np.float32(detail_threshold(ky, kx, config.detail_sigmas))
    sharpens = config.max_history > 1  # else no pixel has history to sharpen with
    step = _DetailStep(detail, along, ky, threshold, sharpens)
    # a history scaled up by the brightness ratio carries up to ratio times the (shot)
    # noise variance the model gives at its new level
    cy, cx = (1, 1) if noise is None else noise.cell
    if strip_rows % cy:
        raise ValueError(f"fuse: cells of {cy} rows do not divide strips of {strip_rows}")
    settings = _FuseSettings(window[0] // 2, window[1] // 2, int(config.widen), inv_k2, scale, floor_weight, separate,
                             max(scale, np.float32(1)), cy, cx, noise is not None and noise.kept)

    def inner(core: slice) -> slice:
        """The strip's rows whose detail window lies within it (mirrored at the frame's ends): the
        update sharpens them as it goes, while their evidence and fused readings are in cache."""
        if not (detail and inline) or core.stop - core.start <= 2 * radius:
            return slice(core.start, core.start)
        return slice(core.start if core.start == 0 else core.start + radius,
                     core.stop if core.stop == h else core.stop - radius)

    def outer(core: slice) -> list[slice]:
        """The strip's rows the update does not sharpen (:func:`inner`), in order: once the strips
        around hold the rows their window reads."""
        done = inner(core)
        return [rows for rows in (slice(core.start, done.start), slice(done.stop, core.stop))
                if rows.stop > rows.start]

    def _skipped(core: slice, k: int) -> tuple:
        """:class:`_Skipped`'s fields of a strip (``core``, the ``k``-th)."""
        start = found.starts[k]
        return (kept, state.bound[core], tested_variance[core], state.censored[core], unstable_k2, bool(same),
                new_censored[core], found.mark[core], found.ys[start:], found.xs[start:], found.counts[k])

    # (the kernel takes each NamedTuple's fields as a plain tuple: :func:`_fuse_strip_fields`)
    frame_fields = tuple(tables), tuple(settings), tuple(step), tuple(_NO_SKIPPED)

    def update(core: slice, short: np.ndarray | None) -> int:
        """Test, confirm, update and sharpen the strip's rows (:func:`_fuse_strip`), reading its
        halo's rows too; returns its count of moving pixels."""
        top, stop = max(core.start - halo, 0), min(core.stop + halo, h)
        ext = slice(top, stop)
        done = inner(core)
        frame_image = image[core]
        if same and kept[core].any():
            if kept[core].all():
                frame_image = state.mean[core]
            else:
                for a, b in predicted:
                    a, b = max(a, core.start), min(b, core.stop)
                    if a < b:
                        image[a:b] = state.mean[a:b]
        count = _fuse_strip_fields((core.start - top, core.start, done.start, done.stop, h),  # _StripRows
                                   (tested[ext], history[ext], state.weight[ext], tested_variance[ext],  # _Halo
                                    bound[ext], state.bound[ext], frame.censored[ext], state.censored[ext]),
                                   (state.weight[core], state.mean[core], state.own[core], history[core],  # _History
                                    _NO_TABLE if own_var is None else state.own_variance[core]),
                                   (frame_image, frame.signal[core], frame.censored[core], tested[core],  # _Frame
                                    share.cells, share.channels), frame_fields[0],
                                   (motion[core], reset[core], weight[core], fused[core], own[core],  # _Outputs
                                    fused_test[core], evidence[core], out[core],
                                    _NO_ROWS if own_var is None else own_var[core],
                                    _NO_ROWS if noise is None else noise.spread[core],
                                    _NO_ROWS if noise is None else noise.floor[core.start // cy:-(-core.stop // cy)],
                                    _NO_COUNTS if row_counts is None else row_counts[core]),
                                   frame_fields[1], frame_fields[2],
                                   frame_fields[3] if found is None else _skipped(core, strip_index[core.start]))
        if inconsistency is not None and not detail:  # output only: the history keeps estimates of one kind
            out[core] = fused[core]
            _replace(*flat(reset[core], inconsistency._flagged[core], short, out[core], motion[core]))
        elif inconsistency is not None and done.stop > done.start:
            _replace(*flat(reset[done], inconsistency._flagged[done], shortest[done], out[done], motion[done]))
        return count

    limit = config.global_motion * motion.size
    lock = threading.Lock()
    moved = [0]  # moving pixels of the strips tested so far

    def strip(core: slice) -> None:
        with lock:
            if moved[0] > limit:  # the frame restarts: nothing to do
                return
        short = None
        if inconsistency is not None:  # while the strip's rows are in cache; the estimate only for the output
            short = (shortest[core] if shortest is not None
                     else np.empty((core.stop - core.start, image.shape[1]), np.float32))
            inconsistency.test(core, short)
        count = update(core, short)  # (a strip that takes the count past the limit is updated for nothing)
        with lock:
            moved[0] += count

    def sharpen_strip(core: slice) -> None:
        """The detail step of rows the update did not sharpen, once the evidence of their rows and a
        window around them is in."""
        if inline:  # the evidence is summed along rows: down the columns in the pass
            _detail_rows(evidence, core.start, core.stop, step, fused, own, reset, out)
        else:
            ext = slice(max(core.start - radius, 0), min(core.stop + radius, h))
            local = smooth(evidence[ext], ky, kx)[core.start - ext.start:core.stop - ext.start]
            _detail_pass(*flat(np.ascontiguousarray(local), fused[core], own[core], reset[core], out[core]),
                         threshold, sharpens)
        if inconsistency is not None:  # output only: the history keeps estimates of one kind
            _replace(*flat(reset[core], inconsistency._flagged[core], shortest[core], out[core], motion[core]))

    if detail and executor is None and workers == 1:
        # on one thread, the detail step of the rows the update left follows as soon as the next
        # strips hold the rows its window reads, while they are still in cache
        ready, left = 0, []
        for i, core in enumerate(strips):
            strip(core)
            left += outer(core)
            last = i == len(strips) - 1
            while ready < len(left) and (last or left[ready].stop + radius <= core.stop):
                if moved[0] <= limit:  # else the frame restarts: nothing to do
                    sharpen_strip(left[ready])
                ready += 1
    else:
        map_on(executor if executor is not None else workers, strip, strips)
        if detail and moved[0] <= limit:
            map_on(executor if executor is not None else workers, sharpen_strip,
                   [rows for core in strips for rows in outer(core)])
    if moved[0] > limit:
        # the camera moved: what was not flagged moved below the noise; every pixel
        # restarts from this frame, as a stream's first frame does
        if predicted:
            frame = complete()
        return _restart(frame, inconsistency, ratio, np.ones(image.shape, bool))
    state = TemporalState(fused, own, weight, bound, new_censored, fused_test if separate else None, own_var)
    # the update applied the within-frame test's finding to the output where it reset the history
    return Fused(out, motion, weight, ratio, state, OutputVariance(variance, weight, inconsistency, reset), reset,
                 found, noise, row_counts)


def _restart(frame: FrameEstimate, inconsistency: Inconsistency | None, ratio: float, motion: np.ndarray) -> Fused:
    """Every pixel restarts from this frame (a stream's first frame, or the camera moved); motion: the mask to report."""
    fresh = start(frame)
    image = frame.image
    if inconsistency is not None:
        image = inconsistency.apply(image)
        motion = motion | inconsistency.flagged
    return Fused(image, motion, fresh.weight, ratio, fresh, OutputVariance(frame.variance, None, inconsistency),
                 np.ones(image.shape, bool))


@kernel
def _test_pixel(x, mean, weight, variance, bound, old_bound, grown, scale, inv_k2):
    """(flagged, unstable) of one pixel: see :func:`fuse` (scale: the brightness ratio applied to the history)."""
    m = mean * scale
    d = x - m
    flagged = d * d * inv_k2 > (weight + np.float32(1)) * variance
    # A lower bound still proves motion one way: a frame's bound far above the
    # history, or a history's bound far above the frame.
    proven = flagged and bound != old_bound and (x > m) == bound
    unstable = grown or bound or old_bound
    return (flagged and not unstable) or proven, unstable


@kernel
def _moving_rows(flagged, flagged_rows, first, widen, motion):
    """motion (the core rows ``first:first + len(motion)`` of the strip) = the ``flagged`` pixels of the
    strip with a flagged 8-neighbour (none beyond the strip), widened by a square of ``2 widen + 1``;
    ``flagged_rows``: the count flagged per row (rows without any are skipped). Returns motion's count."""
    motion[:] = False
    count = 0
    for r in range(flagged.shape[0]):
        count += _paint_row(flagged, flagged_rows, r, flagged.shape[0], first, widen, motion)
    return count


@kernel
def _paint_row(flagged, flagged_rows, r, rows, first, widen, motion):
    """:func:`_moving_rows` of the strip's row ``r``: its confirmed pixels (8-neighbours among the
    strip's first ``rows`` rows) widened into ``motion``; returns the count newly set. Confirmed
    pixels whose squares overlap along the row are painted as one span (moving regions are runs)."""
    if flagged_rows[r] == 0:
        return 0
    cols = flagged.shape[1]
    top, bottom = max(r - widen, first), min(r + widen, first + motion.shape[0] - 1)
    if top > bottom:  # its square does not reach the core rows
        return 0
    count = 0
    start, stop = 0, -1  # the span [start, stop) of columns painted next
    for c in range(cols):
        if not flagged[r, c]:
            continue
        confirmed = False
        for rr in range(max(r - 1, 0), min(r + 2, rows)):
            if flagged_rows[rr] == 0:
                continue
            for cc in range(max(c - 1, 0), min(c + 2, cols)):
                if (rr != r or cc != c) and flagged[rr, cc]:
                    confirmed = True
        if not confirmed:
            continue
        left, right = max(c - widen, 0), min(c + widen + 1, cols)
        if left > stop:  # a gap: paint the span so far
            count += _paint_span(motion, top - first, bottom - first, start, stop)
            start = left
        stop = right
    return count + _paint_span(motion, top - first, bottom - first, start, stop)


@kernel
def _paint_span(motion, top, bottom, start, stop):
    """motion[top:bottom + 1, start:stop] = True; the count newly set (0 for an empty span)."""
    count = 0
    for rr in range(top, bottom + 1):
        row = motion[rr]
        for cc in range(start, stop):
            count += not row[cc]
            row[cc] = True
    return count


@kernel
def _grown_row(changed, changed_rows, start, stop, wx, column, grown):
    """grown (W,) = the reading's censoring changed within rows ``start:stop`` of ``changed`` and
    ``wx`` columns either side (a dilation whose border repeats the edge: what lies beyond adds
    nothing); ``changed_rows``: their counts; ``column``: (W,) scratch."""
    total = 0
    for i in range(start, stop):
        total += changed_rows[i]
    if total == 0:
        grown[:] = False
        return
    column[:] = False
    for i in range(start, stop):
        if changed_rows[i]:
            row = changed[i]
            for c in range(column.size):
                column[c] = column[c] | row[c]
    grown[:] = column
    cols = column.size
    for x in range(1, min(wx, cols - 1) + 1):  # shifted slices, so that LLVM vectorises the loops
        inner = cols - x
        left, right = grown[:inner], column[x:]
        for c in range(inner):
            left[c] = left[c] | right[c]
        left, right = grown[x:], column[:inner]
        for c in range(inner):
            left[c] = left[c] | right[c]


class _StripRows(NamedTuple):
    """Where a strip of :func:`fuse` lies (ints).

    Attributes:
        keep: the strip's first row among the rows of :class:`_Halo`.
        first_row: the frame row of the strip's first row; frame_rows: the frame's rows.
        sharp_first, sharp_stop: the frame rows ``sharp_first:sharp_stop`` the pass sharpens, whose detail
            window's rows are the strip's too (mirrored at the ends of the frame); none if stop <= first.
    """

    keep: int
    first_row: int
    sharp_first: int
    sharp_stop: int
    frame_rows: int


class _Halo(NamedTuple):
    """The rows the noise test of :func:`_fuse_strip` reads: (E, W) rows of the strip with its halo.

    Attributes:
        image, mean: float32, the frame's tested estimate (:attr:`FrameEstimate.tested`) and the history's.
        weight: float32, the history's weight 1 / n; variance: float32, the tested estimate's variance.
        bound, old_bound: bool, the frame's and the history's lower bounds.
        censored, old_censored: bool, their censored readings; a reading whose censoring changed makes its
            window (``wy`` rows, ``wx`` columns either side, within these rows) unstable.
    """

    image: np.ndarray
    mean: np.ndarray
    weight: np.ndarray
    variance: np.ndarray
    bound: np.ndarray
    old_bound: np.ndarray
    censored: np.ndarray
    old_censored: np.ndarray


class _History(NamedTuple):
    """The old state of a strip's rows, which :func:`_update_row` reads: float32 (R, W) rows of
    :class:`TemporalState`'s weight (1 / n), mean, own, tested estimate (``mean`` unless the test
    has a history of its own) and own variance (of no rows, :data:`_NO_TABLE`, without one)."""

    weight: np.ndarray
    mean: np.ndarray
    own: np.ndarray
    test: np.ndarray
    own_variance: np.ndarray


class _Frame(NamedTuple):
    """The new frame's rows of a strip, which :func:`_update_row` reads: (R, W) rows of
    :class:`FrameEstimate`'s image (float32), signal s (float32), censored (bool), tested estimate
    (float32, read where ``separate``); and its share error by cell, the whole frame's (:class:`ShareError`'s
    cells and channels; cells of no planes without one)."""

    image: np.ndarray
    signal: np.ndarray
    censored: np.ndarray
    tested: np.ndarray
    share_cells: np.ndarray
    share_channels: np.ndarray


class _Tables(NamedTuple):
    """The frame's row-phase tables (:class:`FrameEstimate`), which :func:`_update_row` reads.

    Attributes:
        exposures: float32 (P, W), 1 / e by row phase; or, without tables, (H, W) e of each pixel
            (:attr:`FrameEstimate.exposure`), inverted as read (:func:`_inverse_at`).
        own_slope, own_floor: float32 (P, W) by row phase, one own reading's variance ``own_slope * L +
            own_floor``; or of no rows (:data:`_NO_TABLE`): 1 / e times ``slope_scale``, and squared
            times ``floor_scale`` (float32 scalars, 0 with tables).
    """

    exposures: np.ndarray
    own_slope: np.ndarray
    own_floor: np.ndarray
    slope_scale: np.float32
    floor_scale: np.float32


class _Outputs(NamedTuple):
    """What :func:`_fuse_strip` writes: (R, W) rows of the strip.

    Attributes:
        motion, reset: bool, the moving pixels (flagged, confirmed, widened), and those that take the
            frame's values without their history.
        weight: float32, the new weight (1/n -> 1/(n + 1), at least ``floor_weight``, 1 where reset).
        fused, own, fused_test: float32, the running means of the image, the own readings and (where
            ``separate``) the tested estimate.
        evidence: float32, the detail step's evidence summed along rows, written only for the rows the
            later detail step reads (all when the strip sharpens none).
        out: float32, the output, in the rows the pass sharpens.
        own_variance: float32, the running mean of the own readings' variance (:class:`TemporalState`;
            of no rows without one).
        spread, floor: float32, :class:`LuminanceNoise`'s (``spread`` updated in place; ``floor``: the strip's
            cell rows), or of no rows without one.
        row_counts: int64 (R, 2), in the rows of frame rows that are multiples of :data:`COUNTED_STEP`: the row's
            moving pixels and its pixels whose new weight is above ``floor_weight`` (other rows not written); of no
            rows: not counted.
    """

    motion: np.ndarray
    reset: np.ndarray
    weight: np.ndarray
    fused: np.ndarray
    own: np.ndarray
    fused_test: np.ndarray
    evidence: np.ndarray
    out: np.ndarray
    own_variance: np.ndarray
    spread: np.ndarray
    floor: np.ndarray
    row_counts: np.ndarray


class _FuseSettings(NamedTuple):
    """A frame's settings of :func:`_fuse_strip` and :func:`_update_row`, the same for every strip.

    Attributes:
        wy, wx: int, the half height and width of the window a changed censoring makes unstable.
        widen: int, ``config.widen``; inv_k2: float32, 1 / k^2 of the noise test.
        scale: float32, the brightness ratio applied to the history.
        floor_weight: float32, 1 / max_history; separate: bool, the test has a history of its own.
        noisier: float32, max(scale, 1): a history scaled up by the brightness ratio carries up to
            ratio times the (shot) noise variance the model gives at its new level.
        cy, cx: int, the cells of :class:`LuminanceNoise`'s floor (1 without one); kept: bool, its ``kept``.
    """

    wy: int
    wx: int
    widen: int
    inv_k2: np.float32
    scale: np.float32
    floor_weight: np.float32
    separate: bool
    noisier: np.float32
    cy: int
    cx: int
    kept: bool


class _Skipped(NamedTuple):
    """The rows the method skipped (:func:`fuse`'s ``predicted``) as :func:`_skipped_row` judges their resets.

    Attributes:
        rows: bool (H,), the frame's skipped rows; of no rows: none (nothing below is read or written).
        old_bound, old_censored: bool (R, W), the strip's rows of the history's lower bounds and censoring.
        variance: float32 (R, W), the frame's tested estimate's variance.
        inv_k2: float32, 1 / k^2 of the looser test; keep: bool, a reset pixel may keep its history (no
            brightness correction).
        censored: bool (R, W), written: the new history's censoring, the frame's but where a pixel keeps its
            history's.
        mark: int8 (R, W), written: :attr:`SkippedResets.mark`.
        ys, xs: intp, written from 0 on: the strip's pixels marked 2 (frame coordinates), ``tally[0]`` of them.
        tally: int64 (2,), counted: the strip's pixels marked 2 and 1.
    """

    rows: np.ndarray
    old_bound: np.ndarray
    variance: np.ndarray
    old_censored: np.ndarray
    inv_k2: np.float32
    keep: bool
    censored: np.ndarray
    mark: np.ndarray
    ys: np.ndarray
    xs: np.ndarray
    tally: np.ndarray


#: :class:`_Skipped` of a frame without skipped rows.
_NO_SKIPPED = _Skipped(np.empty(0, bool), np.empty((0, 0), bool), _NO_ROWS, np.empty((0, 0), bool), np.float32(0),
                       False, np.empty((0, 0), bool), np.empty((0, 0), np.int8), np.empty(0, np.intp),
                       np.empty(0, np.intp), np.zeros(2, np.int64))


class _DetailStep(NamedTuple):
    """A frame's settings of the detail step (:func:`_update_row`, :func:`_sharpen_row`).

    Attributes:
        enabled: bool, the detail step runs (the update writes the evidence).
        along, kernel_y: float32, the symmetric kernels of the evidence's window along its row
            (numerics._symmetric_row; a single tap of 1: as it is) and down the columns.
        threshold: float32, on the window mean (:func:`detail_threshold`).
        sharpens: bool, pixels have history to sharpen with (else the output is the fused image).
    """

    enabled: bool
    along: np.ndarray
    kernel_y: np.ndarray
    threshold: np.float32
    sharpens: bool


@kernel
def _fuse_strip(strip, halo, history, frame, tables, outputs, settings, step, skipped):
    """One strip of :func:`fuse` in one pass down its rows: the noise test, confirmation and
    widening (``motion``, ``reset``), the running means (:func:`_update_row`) and the detail step.
    Returns the strip's count of moving pixels.

    ``strip``: :class:`_StripRows`; ``halo``: :class:`_Halo`, the rows the test reads; ``history``,
    ``frame``, ``tables``: what the update reads (:class:`_History`, :class:`_Frame`, :class:`_Tables`);
    ``outputs``: :class:`_Outputs`; ``settings``: :class:`_FuseSettings`; ``step``: :class:`_DetailStep`;
    ``skipped``: :class:`_Skipped`, the skipped rows' resets judged as each row is updated.
    Flagged pixels count as moving where an 8-neighbour is flagged too (within the halo's rows),
    widened by ``widen``. Each row is updated once every row whose widening reaches it is tested, a
    few rows after its own test, and sharpened ``kernel_y``'s radius rows later (:func:`_detail_rows`
    into ``out``), so that each row is read from memory once and its results are still in cache when
    the next step reads them. The evidence goes to a ring of the window's rows, and to ``evidence``
    only for the rows the later detail step reads.
    """
    keep, first_row, sharp_first, sharp_stop, frame_rows = strip
    (test_image, test_mean, test_weight, test_variance, test_bound, test_old_bound, test_censored,
     test_old_censored) = halo
    motion, reset, fused, own = outputs.motion, outputs.reset, outputs.fused, outputs.own
    evidence, out = outputs.evidence, outputs.out
    wy, wx, widen, inv_k2, scale = settings.wy, settings.wx, settings.widen, settings.inv_k2, settings.scale
    detail, kernel_y = step.enabled, step.kernel_y
    rows_e, cols = test_image.shape
    rows = frame.image.shape[0]
    changed = np.empty((rows_e, cols), np.bool_)
    changed_rows = np.empty(rows_e, np.intp)
    flagged = np.empty((rows_e, cols), np.bool_)
    flagged_rows = np.empty(rows_e, np.intp)
    column, grown = np.empty(cols, np.bool_), np.empty(cols, np.bool_)
    row, local = np.empty(cols, np.float32), np.empty(cols, np.float32)
    a = kernel_y.size // 2
    # the evidence of the last rows, the detail window's: frame row x in ring[(x - first_row) % len(ring)]
    ring = np.empty((2 * a + 1, cols), np.float32)
    # the luminance noise floor's sums (spread, pixels below weight 1) of the cell row's rows made so far (``made``
    # of them); its cells (``cells``, ``marked[:n_marked]``) whose pixels changed in the rows kept
    total, counted = np.zeros(cols, np.float32), np.zeros(cols, np.float32)
    cells, marked = np.zeros(cols, np.bool_), np.empty(cols, np.intp)
    made, n_marked = 0, 0
    motion[:] = False
    count = 0
    known = 0  # rows whose censoring change is known
    following = 0  # the next strip row to update
    for t in range(rows_e + 1):
        if t < rows_e:
            while known < min(t + wy + 1, rows_e):
                n = 0
                for c in range(cols):
                    d = test_censored[known, c] != test_old_censored[known, c]
                    changed[known, c] = d
                    n += d
                changed_rows[known] = n
                known += 1
            _grown_row(changed, changed_rows, max(t - wy, 0), min(t + wy + 1, rows_e), wx, column, grown)
            core = keep <= t < keep + rows
            n = 0
            for c in range(cols):
                f, unstable = _test_pixel(test_image[t, c], test_mean[t, c], test_weight[t, c], test_variance[t, c],
                                          test_bound[t, c], test_old_bound[t, c], grown[c], scale, inv_k2)
                flagged[t, c] = f
                n += f
                if core:
                    reset[t - keep, c] = f or unstable
            flagged_rows[t] = n
        if t >= 1:  # row t - 1's neighbours are tested
            count += _paint_row(flagged, flagged_rows, t - 1, rows_e, keep, widen, motion)
        # rows every widened row that reaches them has painted
        last = rows if t == rows_e else min(t - widen - keep, rows)
        while following < last:
            slot = ring[following % ring.shape[0]]
            _update_row(following, first_row, history, frame, tables, outputs, settings, step, slot, row)
            if skipped.rows.size:  # (after the update's every read of the row's weight, own readings and test)
                _skipped_row(following, first_row, history, frame, outputs, settings, skipped)
            if outputs.spread.shape[0]:  # (after the skipped row's kept weights)
                g = first_row + following
                if skipped.rows.size > 0 and skipped.rows[g]:
                    n_marked = _kept_spread_row(following, history, outputs, settings.cx, cells, marked, n_marked)
                else:
                    _spread_row(following, history, frame, outputs, settings.scale, total, counted)
                    made += 1
                if (g + 1) % settings.cy == 0 or g + 1 == frame_rows:  # the cell row's last
                    _floor_cells(g // settings.cy, first_row, outputs, settings, made, cells, marked[:n_marked], total,
                                 counted)
                    made, n_marked = 0, 0
            g = first_row + following
            if outputs.row_counts.shape[0] and g % COUNTED_STEP == 0:  # (the row's motion is painted, its weight final)
                _count_row(motion[following], outputs.weight[following], settings.floor_weight,
                           outputs.row_counts[following])
            if detail and (sharp_stop <= sharp_first or g < sharp_first + a or g >= sharp_stop - a):
                evidence[following] = slot  # read by the detail step of rows it does not sharpen
            if sharp_first <= g - a < sharp_stop:  # the rows below it are in
                _sharpen_row(ring, g - a, first_row, frame_rows, step, fused, own, reset, out, local)
            following += 1
    for g in range(max(sharp_first, first_row + rows - a), sharp_stop):  # at the frame's bottom
        _sharpen_row(ring, g, first_row, frame_rows, step, fused, own, reset, out, local)
    return count


@kernel
def _count_row(motion, weight, floor_weight, out):
    """out[0] = the moving pixels of a row (``motion``, bool (W,)), out[1] = its pixels of ``weight`` (float32 (W,))
    above ``floor_weight`` (its unsettled pixels, n < max_history)."""
    moving, unsettled = 0, 0
    for c in range(motion.size):
        moving += motion[c]
        unsettled += weight[c] > floor_weight
    out[0], out[1] = moving, unsettled


@kernel
def _fuse_strip_fields(strip, halo, history, frame, tables, outputs, settings, step, skipped):
    """:func:`_fuse_strip` of plain tuples, each the fields of its NamedTuple in order: numba's dispatcher types a
    plain tuple of arrays in C, a NamedTuple in Python, array by array (30-40 us a call in a colour stream, 10
    calls a frame, against about 10 us)."""
    return _fuse_strip(_StripRows(*strip), _Halo(*halo), _History(*history), _Frame(*frame), _Tables(*tables),
                       _Outputs(*outputs), _FuseSettings(*settings), _DetailStep(*step), _Skipped(*skipped))


@kernel
def _update_row(r, first_row, history, frame, tables, outputs, settings, step, evidence, row):
    """The running means of row ``r`` of a strip starting at frame row ``first_row``; also sets
    ``reset`` where ``motion`` is (:class:`_Outputs`). ``row``: (W,) scratch; ``evidence``: the row's, (W,).

    Reads ``history`` (:class:`_History`), ``frame`` (:class:`_Frame`), ``tables`` (:class:`_Tables`),
    ``settings`` (:class:`_FuseSettings`) and ``step`` (:class:`_DetailStep`). Writes weight (1/n ->
    1/(n + 1), at least ``floor_weight``, 1 where reset), the fused image and own readings; with
    ``separate`` the running mean of the tested estimate with its history (``fused_test``); with an own
    variance (:class:`TemporalState`) its running mean; with the detail step the evidence: (own - fused)^2
    over the fused own reading's variance (one reading's, from the row-phase tables, times the weight and
    ``noisier``), summed along its row with the symmetric kernel ``along``; with a ``share_error`` its share
    of the fused value squared adds to that variance (:class:`FrameEstimate`). Row by row, while the row's
    results are still in cache: the running means in one loop (the tested estimate's and the own variance's
    in loops of their own took x1.1 CPU colour, re-reading the row's weights, estimates and per-pixel
    exposures), the evidence in one of its own.
    """
    old_weight, old_mean, old_own, old_test, old_own_variance = history
    image, signal, censored, tested, share_cells, share_channels = frame
    exposures, own_slope, own_floor, slope_scale, floor_scale = tables
    motion, reset, weight, fused, own = outputs.motion, outputs.reset, outputs.weight, outputs.fused, outputs.own
    fused_test = outputs.fused_test
    floor_weight, scale, separate, noisier = settings.floor_weight, settings.scale, settings.separate, settings.noisier
    detail, along = step.enabled, step.along
    one, zero = np.float32(1), np.float32(0)
    period = exposures.shape[0]
    table_rows = own_slope.shape[0]
    per_pixel = table_rows == 0  # (:class:`_Tables`: ``exposures`` holds e)
    p = (first_row + r) % period
    own_variance = outputs.own_variance
    tracked = own_variance.shape[0] > 0
    for c in range(image.shape[1]):
        restart = reset[r, c] or motion[r, c]
        reset[r, c] = restart
        w = one if restart else _maximum(old_weight[r, c] / (old_weight[r, c] + one), floor_weight)
        weight[r, c] = w
        x = image[r, c]
        fused[r, c] = _running_mean(old_mean[r, c], x, w, scale)
        inverse = _inverse_at(exposures, p, c, per_pixel)
        own[r, c] = _running_mean(old_own[r, c], _own_reading(signal[r, c], inverse, censored[r, c], x), w, scale)
        if separate:
            fused_test[r, c] = _running_mean(old_test[r, c], tested[r, c], w, scale)
        if tracked:
            # exposures that change from frame to frame (a colour frame's e' = e k): the fused own readings'
            # variance is the running mean of each frame's, at its estimate; no row-phase tables
            v = _own_reading_variance(inverse, x, slope_scale, floor_scale)
            own_variance[r, c] = _running_mean(old_own_variance[r, c], v, w, one)
    if detail:
        if share_cells.shape[0]:  # and an error of the own readings that no frame count averages
            _share_row(share_cells, share_channels, first_row + r, row)  # (the row's share errors, then its terms)
            for c in range(image.shape[1]):
                f = _maximum(fused[r, c], zero)
                d = own[r, c] - fused[r, c]
                row[c] = d * d / (own_variance[r, c] * weight[r, c] * noisier + row[c] * f * f)
        elif table_rows:
            q = (first_row + r) % table_rows
            for c in range(image.shape[1]):
                f = fused[r, c]
                d = own[r, c] - f
                row[c] = d * d / ((own_slope[q, c] * _maximum(f, zero) + own_floor[q, c]) * weight[r, c]
                                  * noisier)
        else:
            for c in range(image.shape[1]):
                f = fused[r, c]
                d = own[r, c] - f
                i = _inverse_at(exposures, p, c, per_pixel)
                row[c] = d * d / ((i * slope_scale * _maximum(f, zero) + i * i * floor_scale) * weight[r, c]
                                  * noisier)
        _symmetric_row(row, along, evidence)


@kernel(inline="always")
def _skipped_row(r, first_row, history, frame, outputs, settings, skipped):
    """Row ``r`` (of a strip from frame row ``first_row``; updated) of the new history's censoring and of the skipped
    rows' marks (:class:`_Skipped`). In a skipped row, a reset pixel takes this frame's estimate (marked 2, listed)
    where it moved, the history is a lower bound, the window holds no uncensored reading (an infinite variance),
    the tested estimates differ by more than 1 / sqrt(``skipped.inv_k2``) noise deviations (the fusion's test,
    looser: it does not apply where a reading in the window crossed the censor level, whose window mean then shifts
    beyond its noise alone) or there is no keeping (``skipped.keep``: the light changed); every other keeps its
    history (marked 1): weight, own readings and tested estimate (times the ratio) and censoring as they were (its
    mean is the history's already)."""
    mark, censored, new = skipped.mark[r], skipped.censored[r], frame.censored[r]
    for c in range(mark.size):
        censored[c] = new[c]
        mark[c] = 0
    if not skipped.rows[first_row + r]:
        return
    reset, motion, weight, own = outputs.reset[r], outputs.motion[r], outputs.weight[r], outputs.own[r]
    fused_test = outputs.fused_test[r]
    old_weight, old_own, old_test = history.weight[r], history.own[r], history.test[r]
    old_bound, variance, old_censored = skipped.old_bound[r], skipped.variance[r], skipped.old_censored[r]
    tested = frame.tested[r]
    scale, inv_k2, separate = settings.scale, skipped.inv_k2, settings.separate
    one = np.float32(1)
    tally = skipped.tally
    for c in range(mark.size):
        if not reset[c]:
            continue
        d = tested[c] - old_test[c] * scale
        v = variance[c]
        differs = d * d * inv_k2 > (old_weight[c] + one) * v or v == np.inf
        if motion[c] or old_bound[c] or differs or not skipped.keep:
            mark[c] = 2
            n = tally[0]
            skipped.ys[n], skipped.xs[n] = first_row + r, c
            tally[0] = n + 1
        else:
            mark[c] = 1
            tally[1] += 1
            weight[c] = old_weight[c]
            own[c] = old_own[c] * scale
            if separate:
                fused_test[c] = old_test[c] * scale
            censored[c] = old_censored[c]


@kernel(inline="always")
def _spread_row(r, history, frame, outputs, scale, total, counted):
    """Row ``r`` of :class:`LuminanceNoise`'s spread (:class:`_Outputs`), in place: :func:`noise_evidence` of the
    row's estimate, history and weights (the brightness ratio ``scale``); added to the floor's sums ``total`` (the
    spread) and ``counted`` (pixels of weight below 1), (W,) each."""
    spread, weight = outputs.spread[r], outputs.weight[r]
    image, mean, old_weight = frame.image[r], history.mean[r], history.weight[r]
    one, zero = np.float32(1), np.float32(0)
    for c in range(spread.size):
        w = weight[c]
        value = noise_evidence(image[c], mean[c], old_weight[c], w, spread[c], scale)
        spread[c] = value
        total[c] += value
        counted[c] += one if w < one else zero


#: Columns :func:`_kept_spread_row` looks at together: a loop that vectorises finds the few that changed.
_CHUNK = 64


@kernel(inline="always")
def _kept_spread_row(r, history, outputs, cx, cells, marked, n):
    """Row ``r`` of :class:`LuminanceNoise`'s spread where the method skipped the row: the last frame's evidence,
    in place, 0 where the row's updated weight is 1, which it is where the history's was already (so only a pixel
    whose weight crossed 1 either way changes its floor's terms). The cells (``cx`` columns) of those pixels are
    marked in ``cells`` (bool (W,)) and listed in ``marked`` (intp (W,)) from ``n`` on; returns the new count."""
    spread, weight, old_weight = outputs.spread[r], outputs.weight[r], history.weight[r]
    one, zero = np.float32(1), np.float32(0)
    cols = spread.size
    for c0 in range(0, cols, _CHUNK):
        if c0 + _CHUNK <= cols:  # (a loop of a constant count, over slices: one that vectorises)
            now, before = weight[c0:c0 + _CHUNK], old_weight[c0:c0 + _CHUNK]
            differ = 0
            for k in range(_CHUNK):
                differ += (now[k] < one) != (before[k] < one)
            if differ == 0:
                continue
        for c in range(c0, min(c0 + _CHUNK, cols)):
            fused = weight[c] < one
            if fused != (old_weight[c] < one):
                if not fused:
                    spread[c] = zero
                j = c // cx
                if not cells[j]:
                    cells[j] = True
                    marked[n] = j
                    n += 1
    return n


@kernel(inline="always")
def _floor_cells(i, first_row, outputs, settings, made, cells, marked, total, counted):
    """Cell row ``i`` of :class:`LuminanceNoise`'s floor (:class:`_Outputs`: the strip's, from frame row
    ``first_row``, a cell row's first), of which ``made`` rows were made (:func:`_spread_row`, summed into ``total``
    and ``counted``, (W,) each, set to 0 again here): made anew where any was or the floor was not kept
    (:func:`cell_means` of its rows' spread and their pixels of weight below 1 summed per column in row order),
    else its cells ``marked`` made again alone (the same sums); ``cells`` unmarked."""
    one, zero = np.float32(1), np.float32(0)
    spread, weight, cy, cx = outputs.spread, outputs.weight, settings.cy, settings.cx
    top, stop = i * cy - first_row, min(i * cy + cy - first_row, spread.shape[0])
    floor = outputs.floor[i - first_row // cy]
    cols = floor.size
    for j in marked:
        cells[j] = False
    if made < stop - top and (made or not settings.kept):  # (rows kept too: summed again, in row order)
        total[:] = zero
        counted[:] = zero
        for r in range(top, stop):
            s, w = spread[r], weight[r]
            for c in range(cols):
                total[c] += s[c]
                counted[c] += one if w[c] < one else zero
    if made or not settings.kept:
        cell_means(total, counted, cx, floor)
        total[:] = zero
        counted[:] = zero
        return
    for j in marked:
        t, n = zero, zero
        for c in range(j * cx, min(j * cx + cx, cols)):
            tc, nc = zero, zero
            for r in range(top, stop):
                tc += spread[r, c]
                nc += one if weight[r, c] < one else zero
            t += tc
            n += nc
        t = t / max(n, one)
        for c in range(j * cx, min(j * cx + cx, cols)):
            floor[c] = t


@kernel(inline="always")
def noise_evidence(x, mean, old_weight, weight, old, scale):
    """A pixel's evidence of its luminance noise after this frame (svelive.reconstruction.stream.luminance_noise),
    float32 DN^2: ``old`` (the last frame's) moved towards (x - scale mean)^2 / (1 + old_weight) with the frame's
    weight as a deviation's (the n-th frame's deviation is the pixel's (n - 1)-th: 1 / (n - 1) = w / (1 - w), 1 at
    most; ``weight``: w, the fused weight), 0 where ``weight`` is 1 (no evidence yet)."""
    one = np.float32(1)
    d = x - scale * mean
    term = d * d / (one + old_weight)
    step = min(weight / max(one - weight, np.float32(1e-6)), one)
    return old + step * (term - old) if weight < one else np.float32(0)


@kernel(inline="always")
def cell_means(total, count, cx, out):
    """out (W,) = per cell of ``cx`` columns, the sum of ``total`` over its columns over the sum of ``count``
    (at least 1), float32 (W,) each, summed from 0 in column order (:class:`LuminanceNoise`'s floor)."""
    one, zero = np.float32(1), np.float32(0)
    w, start = out.size, 0
    if cx == 2:  # cells of two columns spelt out: a loop that vectorises (the same sums; a loop of two
        start = w // 2  # per cell left scalar was half of the floor's time)
        for j in range(start):
            t = (zero + total[2 * j]) + total[2 * j + 1]
            n = (zero + count[2 * j]) + count[2 * j + 1]
            t = t / max(n, one)
            out[2 * j] = t
            out[2 * j + 1] = t
    for j in range(start, -(-w // cx)):
        t, n = zero, zero
        for x in range(j * cx, min(j * cx + cx, w)):
            t += total[x]
            n += count[x]
        t = t / max(n, one)
        for x in range(j * cx, min(j * cx + cx, w)):
            out[x] = t


@kernel
def _replace(reset, flagged, short, out, motion):
    """out = ``short`` where a ``reset`` pixel was ``flagged``, which then counts as moving (``motion``
    set); flat arrays (distinct: a second array aliasing ``out`` would keep the loop from vectorising)."""
    for k in range(out.size):
        used = reset[k] & flagged[k]
        a, b = short[k], out[k]
        out[k] = a if used else b
        motion[k] = motion[k] | used


@kernel
def _running_mean(mean, new, weight, scale):
    """scale mean + weight (new - scale mean), float32; equals ``new`` where weight is 1."""
    mean = mean * scale
    return (new - mean) * weight + mean




def detail_threshold(kernel_y: np.ndarray, kernel_x: np.ndarray, sigmas: float) -> float:
    """The detail step's threshold on the window mean of the normalised squared differences z.

    Where the fused own readings differ from the fused estimate by noise alone, each z has
    mean 1 and variance 2 (a chi-square of one degree); their mean over a window of weights
    G (``kernel_y`` x ``kernel_x``, summing to 1) has mean 1 and standard deviation
    sqrt(2 sum G^2). The threshold is ``sigmas`` of those above 1.
    """
    squares = float(np.sum(np.square(kernel_y, dtype=np.float64))) * float(np.sum(np.square(kernel_x,
                                                                                            dtype=np.float64)))
    return 1.0 + sigmas * float(np.sqrt(2.0 * squares))


@kernel
def _detail_rows(evidence, first, stop, step, fused, own, reset, out):
    """:func:`_detail_pass` of rows ``first:stop`` of the (H, W) arrays, ``local`` made here: the window
    mean of ``evidence`` (summed along rows already) down the columns with the symmetric
    ``step.kernel_y`` (:class:`_DetailStep`), rows beyond the frame mirrored, in OpenCV's order
    (numerics._symmetric_row): bit-identical to methods.base.smooth's for kernels of up to
    numerics.INLINE_TAPS taps."""
    local = np.empty(evidence.shape[1], np.float32)
    for r in range(first, stop):
        _sharpen_row(evidence, r, 0, evidence.shape[0], step, fused, own, reset, out, local)


@kernel(inline="always")
def _sharpen_row(evidence, r, first, rows, step, fused, own, reset, out, local):
    """:func:`_detail_rows` of frame row ``r`` of a frame of ``rows`` rows, the arrays holding frame
    rows from ``first`` on (``evidence`` frame row x at ``(x - first) % len(evidence)``: also a ring
    of the rows around ``r``); ``step``: :class:`_DetailStep`; ``local``: (W,) scratch."""
    kernel, threshold, sharpens = step.kernel_y, step.threshold, step.sharpens
    a = kernel.size // 2
    zero, one = np.float32(0), np.float32(1)
    cols, n = local.size, evidence.shape[0]
    centre, kc = evidence[(r - first) % n], kernel[a]
    for c in range(cols):
        local[c] = centre[c] * kc
    for j in range(1, a + 1):
        above = evidence[(reflect_101(r - j, rows) - first) % n]
        below = evidence[(reflect_101(r + j, rows) - first) % n]
        kj = kernel[a + j]
        for c in range(cols):
            local[c] = local[c] + (above[c] + below[c]) * kj
    f_row, o_row, reset_row, out_row = fused[r - first], own[r - first], reset[r - first], out[r - first]
    for c in range(cols):
        f, o, z, restart = f_row[c], o_row[c], local[c], reset_row[c]
        beta = _maximum(one - threshold / z, zero)  # 0 where z is 0 (threshold / 0 = inf)
        sharp = _maximum(f + beta * (o - f), zero)
        out_row[c] = f if restart or not sharpens else sharp


@kernel
def _detail_pass(local, fused, own, reset, out, threshold, sharpens):
    """out = fused + beta (own - fused), beta = max(0, 1 - threshold / local), where the pixel has
    history (not ``reset``, and ``sharpens``), else fused; >= 0. Flat arrays."""
    zero, one = np.float32(0), np.float32(1)
    for k in range(out.size):
        f, o, z, restart = fused[k], own[k], local[k], reset[k]
        beta = _maximum(one - threshold / z, zero)  # 0 where z is 0 (threshold / 0 = inf)
        sharp = _maximum(f + beta * (o - f), zero)
        out[k] = f if restart or not sharpens else sharp


def sharpen(mean: np.ndarray, own: np.ndarray, threshold: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Move a smooth estimate towards each pixel's own readings where they differ beyond noise.

    ``out = mean + w (own - mean)``, ``w = max(0, 1 - threshold / (own - mean)^2)``: a
    non-negative garrote. The smooth estimate ``mean`` has lost resolution (a bias
    b); the pixel's own readings have none but carry noise of variance
    var_own. With ``threshold = var_own`` this is the positive-part James-Stein
    estimate of the MSE-optimal weight b^2 / (b^2 + var_own); the caller passes
    ``sigmas^2 var_own`` (a significance level like the motion test's), because
    the James-Stein weight lets noise through where a few DN of noise are a
    large relative error (dark regions; measured in docs/motion.md).

    Args:
        mean, own, threshold: float32 arrays of one shape (DN, DN, DN^2); the
            threshold must be > 0, an infinite one keeps ``mean``.
        out: where to write the result (a new array when None).

    Returns:
        float32, >= 0.
    """
    mean, own, threshold = (np.ascontiguousarray(a, np.float32) for a in np.broadcast_arrays(mean, own, threshold))
    result = np.empty(mean.shape, np.float32)
    _sharpen_pass(*flat(mean, own, threshold, result))
    if out is None:
        return result
    out[...] = result
    return out


@kernel
def _sharpen_pass(mean, own, threshold, out):
    for k in range(mean.size):
        out[k] = _sharpened(mean[k], own[k], threshold[k])


@kernel
def _sharpened(mean, own, threshold):
    """:func:`sharpen` of one pixel."""
    diff = own - mean
    weight = _maximum(np.float32(1) - threshold / (diff * diff), np.float32(0))  # 0 where own == mean
    return _maximum(diff * weight + mean, np.float32(0))
