"""Per-pixel motion robustness: exposure consistency within a frame, motion-safe fusion across frames.

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
  is static; a pixel whose new estimate disagrees with its history is reset
  to the new estimate at once, so moving objects leave no trail. Global
  brightness changes (lights switched, mains flicker) are first divided out
  with a robust global ratio, so they do not reset every pixel.

Units: radiance in DN at relative exposure 1, variances in DN^2 at exposure 1.
"""

from __future__ import annotations

import threading
from concurrent.futures import Executor
from dataclasses import dataclass
from functools import cached_property, lru_cache

import cv2
import numpy as np

from svelive.errors import SveliveError
from svelive.jit import flat, kernel
from svelive.methods.base import SveInput, binomial_kernel, map_on, smooth, support_size
from svelive.pattern import Pattern


@dataclass(frozen=True)
class MotionConfig:
    """Thresholds of the motion tests.

    Attributes:
        temporal_sigmas: k of the frame-to-history test; 4 gives a Gaussian
            false-alarm rate of 6e-5 per pixel before widening.
        consistency_sigmas: k of the within-frame exposure-consistency test.
        max_history: frames a static pixel averages at most (the memory of the
            recursive average once full: its weight for a new frame is 1 / max_history).
        widen: pixels by which flagged areas grow (a square of 2 widen + 1).
        detail_sigmas: how far beyond its noise a pixel's own fused readings must
            differ from the smooth estimate before they sharpen it (:func:`sharpen`).
        global_motion: fraction of moving pixels above which the whole history restarts.
        compensate_illumination: divide out a global brightness ratio between
            history and frame before testing.
    """

    temporal_sigmas: float = 4.0
    consistency_sigmas: float = 4.0
    max_history: int = 8
    widen: int = 1
    detail_sigmas: float = 3.0
    global_motion: float = 0.5
    compensate_illumination: bool = True

    def __post_init__(self) -> None:
        for name in ("temporal_sigmas", "consistency_sigmas", "detail_sigmas"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise SveliveError(f"motion config: {name} must be > 0, got {value}")
        if int(self.max_history) < 1:
            raise SveliveError(f"motion config: max_history must be >= 1, got {self.max_history}")
        if not 0 <= int(self.widen) <= 16:
            raise SveliveError(f"motion config: widen must be 0..16 pixels, got {self.widen}")


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
    """

    mean: np.ndarray
    own: np.ndarray
    weight: np.ndarray
    bound: np.ndarray
    censored: np.ndarray


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
            whole map, so that the per-pixel pass reads a few rows that stay in cache.
        own_slope, own_floor: float32 (P, W), by row phase likewise, the detail threshold
            for one frame, ``own_slope * L + own_floor`` at radiance L: the own reading's
            variance (1 / (e g) and sigma^2 / e^2) times detail_sigmas^2.
    """

    image: np.ndarray
    variance: np.ndarray
    bound: np.ndarray
    censored: np.ndarray
    signal: np.ndarray
    inverse: np.ndarray
    own_slope: np.ndarray
    own_floor: np.ndarray

    @cached_property
    def own(self) -> np.ndarray:
        """float32 (H, W), each pixel's own reading s / e (``image`` where censored), computed on first use."""
        own = np.empty(self.image.shape, np.float32)
        _own_rows(self.signal, self.inverse, self.censored, self.image, own)
        return own


@kernel
def _own_reading(signal, inverse, censored, image):
    """A pixel's own reading s / e, or the frame's estimate where the reading is censored."""
    return image if censored else signal * inverse


@kernel
def _own_rows(signal, inverse, censored, image, out):
    """out = own readings, (H, W) arrays with ``inverse`` by row phase (P, W)."""
    period = inverse.shape[0]
    for r in range(out.shape[0]):
        p = r % period
        for c in range(out.shape[1]):
            out[r, c] = _own_reading(signal[r, c], inverse[p, c], censored[r, c], image[r, c])


@dataclass(frozen=True)
class OutputVariance:
    """The variance of a fused output, computed when called (float32 (H, W), DN^2).

    The frame's variance times the weight of its frame in each pixel's mean,
    ``weight`` (the history's variance for a static scene with stationary noise;
    None: the frame's as it is), and the shortest exposure's where
    ``replaced = (used, variance)`` says the within-frame test's finding was applied.
    A whole-frame array the live path never reads: computing it on demand saves writing it.
    """

    frame: np.ndarray
    weight: np.ndarray | None = None
    replaced: tuple[np.ndarray, np.ndarray] | None = None

    def __call__(self) -> np.ndarray:
        variance = self.frame
        if self.weight is not None:
            variance = np.empty(self.frame.shape, np.float32)
            np.multiply(self.frame, self.weight, out=variance)
        if self.replaced is not None:
            used, replacement = self.replaced
            variance = np.where(used, replacement, variance)
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
    """

    image: np.ndarray
    motion: np.ndarray
    history: np.ndarray
    illumination_ratio: float
    state: TemporalState
    variance_of: OutputVariance

    @cached_property
    def variance(self) -> np.ndarray:
        """float32 (H, W), the output's variance (:class:`OutputVariance`)."""
        return self.variance_of()


def _grow(mask: np.ndarray, window: tuple[int, int]) -> np.ndarray:
    """Dilate a bool (H, W) mask by a centred (rows, cols) window."""
    return cv2.dilate(mask.view(np.uint8), np.ones(window, np.uint8), borderType=cv2.BORDER_REPLICATE).view(bool)


#: The 8 neighbours of a pixel, as a dilation kernel.
_RING = np.array([[1, 1, 1], [1, 0, 1], [1, 1, 1]], np.uint8)


def _confirmed(flagged: np.ndarray) -> np.ndarray:
    """bool (H, W): flagged pixels with at least one flagged 8-neighbour (none beyond the border)."""
    mask = flagged.view(np.uint8)
    return cv2.bitwise_and(mask, cv2.dilate(mask, _RING)).view(bool)


def _widen(mask: np.ndarray, pixels: int) -> np.ndarray:
    """Dilate a bool (H, W) mask by a (2 pixels + 1)^2 square."""
    if pixels <= 0:
        return mask
    square = np.ones((2 * pixels + 1, 2 * pixels + 1), np.uint8)
    return cv2.dilate(mask.view(np.uint8), square, borderType=cv2.BORDER_REPLICATE).view(bool)


def disagree(a: np.ndarray, var_a: np.ndarray, b: np.ndarray, var_b: np.ndarray, sigmas: float) -> np.ndarray:
    """bool (H, W): ``(a - b)^2 > sigmas^2 (var_a + var_b)``, the noise-model test of two float32 estimates."""
    diff = a - b
    diff *= diff
    tolerance = var_a + var_b
    tolerance *= np.float32(sigmas * sigmas)
    return diff > tolerance


# ----- within one frame -----------------------------------------------------

def _window_kernels(pattern: Pattern) -> tuple[np.ndarray, np.ndarray]:
    """The binomial (rows, columns) kernels of a window holding every phase of the tile."""
    th, tw = pattern.shape
    return binomial_kernel(support_size(th)), binomial_kernel(support_size(tw))


@lru_cache(maxsize=8)
def _shortest_layout(pattern: Pattern, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """For the shortest exposure level: (mask float32, window sum of squared kernel weights), read-only."""
    mask = (pattern.level_index_map(shape) == 0).astype(np.float32)
    ky, kx = _window_kernels(pattern)
    squares = smooth(mask, ky * ky, kx * kx)
    for array in (mask, squares):
        array.setflags(write=False)
    return mask, squares


def shortest_exposure_estimate(inp: SveInput) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Radiance from the shortest exposure's uncensored samples alone, as the ``weighted`` method interpolates one level.

    A binomial window holding every phase of the tile averages the level's
    uncensored readings s / e; the variance is the noise model's at that
    radiance divided by the effective number of samples in the window.

    Returns:
        (estimate float32 (H, W) DN at exposure 1, variance float32 (H, W) DN^2,
        valid bool (H, W): the window held at least one uncensored sample).
    """
    if inp.pattern.pixel_map is not None:
        raise SveliveError("the exposure-consistency test needs a nominal tile, not a per-pixel exposure map")
    mask, squares = _shortest_layout(inp.pattern, inp.shape)
    ky, kx = _window_kernels(inp.pattern)
    exposure = float(inp.pattern.levels[0])
    weights = mask * ~inp.censored
    weight_sum = smooth(weights, ky, kx)
    estimate = smooth(inp.signal * weights, ky, kx)
    valid = weight_sum > 1e-6
    np.divide(estimate, weight_sum * np.float32(exposure), out=estimate, where=valid)
    np.maximum(estimate, 0, out=estimate)
    if inp.censored.any():
        squares = smooth(weights, ky * ky, kx * kx)
    effective = weight_sum * weight_sum / np.maximum(squares, 1e-12)  # (sum w)^2 / sum w^2
    sensor = inp.sensor
    variance = estimate * np.float32(exposure / sensor.effective_gain) + np.float32(sensor.floor_variance)
    variance /= np.maximum(effective, 1e-6) * np.float32(exposure * exposure)
    variance[~valid] = np.inf
    return estimate, variance, valid


@dataclass(frozen=True)
class Inconsistency:
    """The within-frame test's finding: where to rely on the shortest exposure, and its estimate.

    Attributes:
        flagged: bool (H, W), widened pixels whose estimate disagrees with the shortest exposure's.
        image, variance: float32 (H, W), the shortest exposure's estimate and variance.
    """

    flagged: np.ndarray
    image: np.ndarray
    variance: np.ndarray

    def apply(self, image: np.ndarray, variance: np.ndarray,
              where: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(image, variance, used): the shortest exposure's values where flagged (and ``where``), new arrays."""
        image, used = self.apply_image(image, where)
        return image, np.where(used, self.variance, variance), used

    def apply_image(self, image: np.ndarray, where: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(image, used): :meth:`apply` without the variance (:class:`OutputVariance` takes ``used``)."""
        used = self.flagged if where is None else self.flagged & where
        return np.where(used, self.image, image), used


def exposure_consistency(image: np.ndarray, variance: np.ndarray, inp: SveInput,
                         config: MotionConfig) -> Inconsistency:
    """Within-frame test: where does the frame's estimate disagree with the shortest exposure's beyond noise?

    The estimates interpolate different pixels, so at static fine texture they
    also disagree (spatial aliasing, not in the noise model): a caller with a
    history applies the finding only where the temporal test saw motion.

    Args:
        image, variance: float32 (H, W), a single-frame estimate and its variance (DN, DN^2).
        inp: the prepared raw frame it came from.
    """
    short, short_var, valid = shortest_exposure_estimate(inp)
    flagged = disagree(image, variance, short, short_var, config.consistency_sigmas)
    flagged &= valid
    flagged = _widen(flagged, config.widen) & valid
    return Inconsistency(flagged, short, short_var)


# ----- across frames ----------------------------------------------------------

def illumination_ratio(state: TemporalState, image: np.ndarray, variance: np.ndarray, bound: np.ndarray,
                       step: int = 8) -> float:
    """Robust global brightness ratio frame / history: the median of image / mean over well-measured pixels.

    Subsampled every ``step`` pixels; pixels count when both values are at least
    3 noise standard deviations (the frame's) above 0 and neither is a lower bound. Returns 1
    when fewer than 64 pixels qualify.
    """
    h, w = image.shape
    ratios = np.empty(-(-h // step) * -(-w // step), np.float32)
    count = _subsampled_ratios(image, state.mean, variance, bound, state.bound, step, ratios)
    if count < 64:
        return 1.0
    ratio = float(np.median(ratios[:count]))
    return ratio if np.isfinite(ratio) and ratio > 0 else 1.0


@kernel
def _subsampled_ratios(image, mean, variance, bound, old_bound, step, out):
    """Writes image / mean of the well-measured pixels of every ``step``-th row and column
    (row-major) to ``out``; returns their count."""
    nine = np.float32(9)
    count = 0
    for i in range(0, image.shape[0], step):
        for j in range(0, image.shape[1], step):
            a, b, v = image[i, j], mean[i, j], nine * variance[i, j]
            if a * a > v and b * b > v and not (bound[i, j] or old_bound[i, j]):
                out[count] = a / b
                count += 1
    return count


#: Rows per strip of the per-pixel passes: small enough for a strip's arrays to stay in cache
#: from its test to its update.
STRIP_ROWS = 64

#: Global brightness ratios closer to 1 than this are not divided out (far below any noise).
RATIO_TOLERANCE = 2e-3


def start(frame: FrameEstimate) -> TemporalState:
    """A history holding one frame."""
    return TemporalState(frame.image, frame.own, np.ones(frame.image.shape, np.float32), frame.bound, frame.censored)


def fuse(state: TemporalState | None, frame: FrameEstimate, config: MotionConfig, pattern_shape: tuple[int, int],
         inconsistency: Inconsistency | None = None, detail: bool = True, workers: int = 1,
         strip_rows: int = STRIP_ROWS, executor: Executor | None = None) -> Fused:
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
            (svelive.methods.base.map_on); None: one is made for this call.

    With w = 1 / n the history's weight state, a pixel is reset to the frame's
    estimate where the noise test ``(x - mean)^2 > k^2 v (1 + w)`` flags it,
    where either the history or the frame is only a
    lower bound (a bound cannot be averaged), and within a tile window of a
    reading that crossed the censor level. Flagged pixels count as motion when
    a neighbour is flagged too (every estimate spreads over a window, so does
    any real change; isolated flags are mostly noise); motion is widened by
    ``config.widen`` and reset too. When more than ``config.global_motion`` of
    the frame moves, the camera moved: every pixel is reset.
    Elsewhere it takes the running mean with weight 1 / min(n + 1, max_history).
    The history's variance is taken as the frame's variance v times w, as for a
    static scene with stationary noise. The test compares smooth estimates,
    whose loss of resolution is the same in every frame of a static scene and
    so cancels.

    Work is done in strips of ``strip_rows`` rows, small enough for a strip's
    arrays to stay in cache from its test to its update: each strip is tested
    (reading a halo of rows around it for the neighbourhood operations, so strips
    join without a seam), then updated at once unless the moving pixels found so
    far already exceed ``config.global_motion`` of the frame; from then on the
    frame restarts whatever the other strips hold, so they are skipped. The
    global brightness ratio is measured first, on a subsample.
    """
    image, variance, bound = frame.image, frame.variance, frame.bound
    if state is None or state.mean.shape != image.shape:
        return _restart(frame, inconsistency, 1.0, np.zeros(image.shape, bool))
    ratio = illumination_ratio(state, image, variance, bound) if config.compensate_illumination else 1.0
    # mean * 1 is exact: one kernel with and without a brightness correction
    scale = np.float32(ratio) if abs(ratio - 1.0) > RATIO_TOLERANCE else np.float32(1)
    h = image.shape[0]
    rows = max(1, int(strip_rows))
    strips = [slice(top, min(top + rows, h)) for top in range(0, h, rows)]
    window = tuple(support_size(n) for n in pattern_shape)
    # rows a strip's motion mask depends on: censor changes grow by window // 2, then
    # confirmation looks 1 row further, widening ``widen`` more
    halo = window[0] // 2 + 1 + int(config.widen)
    inv_k2 = np.float32(1.0 / config.temporal_sigmas ** 2)
    motion = np.empty(image.shape, bool)
    reset = np.empty(image.shape, bool)

    def test(core: slice) -> int:
        """Motion and reset masks of the strip's rows; returns its count of moving pixels."""
        top, stop = max(core.start - halo, 0), min(core.stop + halo, h)
        ext, keep = slice(top, stop), slice(core.start - top, core.stop - top)
        # A reading that crossed the censor level changes which exposures a method
        # uses nearby, and so its resolution loss: not evidence of motion, but not
        # averageable either (grown by a tile window).
        changed = np.not_equal(frame.censored[ext], state.censored[ext])
        grown = _grow(changed, window) if changed.any() else changed
        flagged = np.empty(changed.shape, bool)
        count = _test_rows(image[ext], state.mean[ext], state.weight[ext], variance[ext], bound[ext],
                           state.bound[ext], grown, scale, inv_k2, flagged, reset[core], keep.start)
        if count == 0:  # nothing flagged near the strip: nothing to confirm or widen
            motion[core] = False
            return 0
        confirmed = _confirmed(flagged)
        if not confirmed.any():  # isolated flags only (noise)
            motion[core] = False
            return 0
        moving = _widen(confirmed, config.widen)[keep]
        motion[core] = moving
        return int(np.count_nonzero(moving))

    fused, own, weight = np.empty_like(image), np.empty_like(image), np.empty_like(image)
    out = np.empty_like(image) if detail else fused
    floor_weight = np.float32(1.0 / config.max_history)

    def update(core: slice) -> None:
        _update_rows(core.start, state.weight[core], motion[core], state.mean[core], state.own[core], image[core],
                     frame.signal[core], frame.censored[core], frame.inverse, frame.own_slope,
                     frame.own_floor, floor_weight, scale, detail, reset[core], weight[core], fused[core], own[core],
                     out[core])

    limit = config.global_motion * motion.size
    lock = threading.Lock()
    moved = [0]  # moving pixels of the strips tested so far

    def strip(core: slice) -> None:
        with lock:
            if moved[0] > limit:  # the frame restarts: nothing to do
                return
        count = test(core)
        with lock:
            moved[0] += count
            restarts = moved[0] > limit
        if not restarts:
            update(core)

    map_on(executor if executor is not None else workers, strip, strips)
    if moved[0] > limit:
        # the camera moved: what was not flagged moved below the noise; every pixel
        # restarts from this frame, as a stream's first frame does
        return _restart(frame, inconsistency, ratio, np.ones(image.shape, bool))
    state = TemporalState(fused, own, weight, bound, frame.censored)
    replaced = None
    if inconsistency is not None:  # output only: the history keeps estimates of one kind
        out, used = inconsistency.apply_image(out, reset)
        motion = motion | used
        replaced = (used, inconsistency.variance)
    return Fused(out, motion, weight, ratio, state, OutputVariance(variance, weight, replaced))


def _restart(frame: FrameEstimate, inconsistency: Inconsistency | None, ratio: float, motion: np.ndarray) -> Fused:
    """Every pixel restarts from this frame (a stream's first frame, or the camera moved); motion: the mask to report."""
    fresh = start(frame)
    image, replaced = frame.image, None
    if inconsistency is not None:
        image, used = inconsistency.apply_image(image)
        motion = motion | used
        replaced = (used, inconsistency.variance)
    return Fused(image, motion, fresh.weight, ratio, fresh, OutputVariance(frame.variance, None, replaced))


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
def _test_rows(image, mean, weight, variance, bound, old_bound, grown, scale, inv_k2, flagged, reset, first):
    """The noise test of a strip with its halo, (R, W) arrays: writes ``flagged`` and, for rows
    ``first:first + len(reset)``, ``reset`` (flagged or unstable); returns the count flagged."""
    count = 0
    for r in range(image.shape[0]):
        core = first <= r < first + reset.shape[0]
        for c in range(image.shape[1]):
            f, unstable = _test_pixel(image[r, c], mean[r, c], weight[r, c], variance[r, c], bound[r, c],
                                      old_bound[r, c], grown[r, c], scale, inv_k2)
            flagged[r, c] = f
            count += f
            if core:
                reset[r - first, c] = f or unstable
    return count


@kernel
def _update_rows(first_row, old_weight, motion, old_mean, old_own, image, signal, censored, inverse,
                 own_slope, own_floor, floor_weight, scale, detail, reset, weight, fused, own, out):
    """The running means of a strip starting at row ``first_row``; also sets ``reset`` where ``motion`` is.

    (R, W) arrays but for inverse, own_slope and own_floor, which are (P, W) by row
    phase (:class:`FrameEstimate`). Writes weight (1/n -> 1/(n + 1), at least
    ``floor_weight``, 1 where reset), the fused image and own readings and, with
    ``detail``, the sharpened output.
    """
    one = np.float32(1)
    history = floor_weight < one  # else no pixel has history to sharpen with
    period = inverse.shape[0]
    for r in range(image.shape[0]):
        p = (first_row + r) % period
        for c in range(image.shape[1]):
            restart = reset[r, c] or motion[r, c]
            reset[r, c] = restart
            w = one if restart else _maximum(old_weight[r, c] / (old_weight[r, c] + one), floor_weight)
            weight[r, c] = w
            x = image[r, c]
            f = _running_mean(old_mean[r, c], x, w, scale)
            fused[r, c] = f
            o = _running_mean(old_own[r, c], _own_reading(signal[r, c], inverse[p, c], censored[r, c], x), w, scale)
            own[r, c] = o
            if detail:
                # a pixel without history (reset, or max_history 1) has nothing to sharpen with
                sharp = history and not restart
                out[r, c] = _sharpened(f, o, (own_slope[p, c] * f + own_floor[p, c]) * w) if sharp else f


@kernel
def _running_mean(mean, new, weight, scale):
    """scale mean + weight (new - scale mean), float32; equals ``new`` where weight is 1."""
    mean = mean * scale
    return (new - mean) * weight + mean


@kernel
def _maximum(a, b):
    """max(a, b) with numpy's NaN propagation from ``a``."""
    return b if a < b else a


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
