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

from concurrent.futures import Executor
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from svelive.errors import SveliveError
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
        own: float32 (H, W), each pixel's own reading s / e (``image`` where censored).
        own_slope, own_floor: float32 (H, W), the detail threshold for one frame,
            ``own_slope * L + own_floor`` at radiance L: the own reading's variance
            (1 / (e g) and sigma^2 / e^2) times detail_sigmas^2.
    """

    image: np.ndarray
    variance: np.ndarray
    bound: np.ndarray
    censored: np.ndarray
    own: np.ndarray
    own_slope: np.ndarray
    own_floor: np.ndarray


@dataclass(frozen=True)
class Fused:
    """One frame's output of :func:`fuse`.

    Attributes:
        image, variance: float32 (H, W), the output radiance and its variance.
        motion: bool (H, W), pixels whose history was reset because the scene moved
            (widened), or that the within-frame test flagged.
        history: float32 (H, W), 1 / n, n = frames in each pixel's mean (min(frames since reset, max_history)).
        illumination_ratio: the global brightness ratio divided out (frame / history).
        state: the history to pass with the next frame.
    """

    image: np.ndarray
    variance: np.ndarray
    motion: np.ndarray
    history: np.ndarray
    illumination_ratio: float
    state: TemporalState


def _grow(mask: np.ndarray, window: tuple[int, int]) -> np.ndarray:
    """Dilate a bool (H, W) mask by a centred (rows, cols) window."""
    return cv2.dilate(mask.view(np.uint8), np.ones(window, np.uint8), borderType=cv2.BORDER_REPLICATE).view(bool)


def _confirmed(flagged: np.ndarray) -> np.ndarray:
    """bool (H, W): flagged pixels with at least one flagged 8-neighbour."""
    counts = cv2.boxFilter(flagged.view(np.uint8), -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
    return flagged & (counts >= 2)


def _widen(mask: np.ndarray, pixels: int) -> np.ndarray:
    """Dilate a bool (H, W) mask by a (2 pixels + 1)^2 square."""
    if pixels <= 0:
        return mask
    kernel = np.ones((2 * pixels + 1, 2 * pixels + 1), np.uint8)
    return cv2.dilate(mask.view(np.uint8), kernel, borderType=cv2.BORDER_REPLICATE).view(bool)


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

    def apply(self, image: np.ndarray, variance: np.ndarray, where: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(image, variance, used): the shortest exposure's values where flagged (and ``where``), new arrays."""
        used = self.flagged if where is None else self.flagged & where
        return np.where(used, self.image, image), np.where(used, self.variance, variance), used


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
    a = image[::step, ::step]
    b = state.mean[::step, ::step]
    var = variance[::step, ::step]
    good = (a * a > 9 * var) & (b * b > 9 * var)
    good &= ~(bound[::step, ::step] | state.bound[::step, ::step])
    if np.count_nonzero(good) < 64:
        return 1.0
    ratio = float(np.median(a[good] / b[good]))
    return ratio if np.isfinite(ratio) and ratio > 0 else 1.0


#: Rows per strip of the per-pixel passes: small enough for the temporaries to stay in cache.
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
        workers: threads over which the strips are spread (numpy and OpenCV release
            the GIL); the result does not depend on it.
        strip_rows: rows per strip (with workers > 1, at least the frame's height over
            2 workers); the result does not depend on it either.
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

    Work is done in strips of ``strip_rows`` rows, small enough for the
    temporaries to stay in cache, in two passes: the tests (each strip reads a
    halo of rows around it for the neighbourhood operations, so strips join
    without a seam), then, once the frame's share of moving pixels is known,
    the update. The global brightness ratio is measured first, on a subsample.
    """
    image, variance, bound = frame.image, frame.variance, frame.bound
    if state is None or state.mean.shape != image.shape:
        motion = np.zeros(image.shape, bool)
        fresh = start(frame)
        if inconsistency is not None:
            image, variance, motion = inconsistency.apply(image, variance)
        return Fused(image, variance, motion, fresh.weight, 1.0, fresh)
    ratio = illumination_ratio(state, image, variance, bound) if config.compensate_illumination else 1.0
    scale = np.float32(ratio) if abs(ratio - 1.0) > RATIO_TOLERANCE else None
    h = image.shape[0]
    rows = max(1, int(strip_rows))
    if workers > 1:
        # two strips per thread: each numpy call then works long enough between the threads'
        # hand-offs of the GIL, which cost more than the cache misses of large strips (measured:
        # 64-row strips on 2 threads took longer than 1 thread; 300-row strips 20 % less)
        rows = max(rows, -(-h // (2 * workers)))
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
        mean = state.mean[ext] if scale is None else state.mean[ext] * scale
        diff = image[ext] - mean
        diff *= diff
        diff *= inv_k2
        tolerance = state.weight[ext] + np.float32(1)
        tolerance *= variance[ext]
        flagged = diff > tolerance
        # A reading that crossed the censor level changes which exposures a method
        # uses nearby, and so its resolution loss: not evidence of motion, but not
        # averageable either. A lower bound still proves motion one way: a frame's
        # bound far above the history, or a history's bound far above the frame.
        either_bound = bound[ext] ^ state.bound[ext]
        proven = flagged & either_bound & ((image[ext] > mean) == bound[ext]) if either_bound.any() else None
        unstable = _grow(frame.censored[ext] ^ state.censored[ext], window)
        unstable |= bound[ext]
        unstable |= state.bound[ext]
        flagged &= ~unstable
        if proven is not None:
            flagged |= proven
        moving = _widen(_confirmed(flagged), config.widen)[keep]
        motion[core] = moving
        np.logical_or(flagged[keep], unstable[keep], out=reset[core])
        return int(np.count_nonzero(moving))

    fused, own, fused_var = np.empty_like(image), np.empty_like(image), np.empty_like(image)
    weight = np.empty_like(image)
    out = np.empty_like(image) if detail else fused
    floor_weight = np.float32(1.0 / config.max_history)

    def run(function, items) -> list:
        return map_on(executor if executor is not None else workers, function, items)

    def update(core: slice) -> None:
        w = weight[core]  # 1/n -> 1/(n + 1), capped, 1 where reset
        np.add(state.weight[core], np.float32(1), out=w)
        np.divide(state.weight[core], w, out=w)
        np.maximum(w, floor_weight, out=w)
        np.copyto(w, np.float32(1), where=reset[core])
        _running_mean(state.mean[core], image[core], w, scale, out=fused[core])
        _running_mean(state.own[core], frame.own[core], w, scale, out=own[core])
        np.multiply(variance[core], w, out=fused_var[core])
        if detail:
            threshold = frame.own_slope[core] * fused[core]
            threshold += frame.own_floor[core]
            threshold *= w
            sharpen(fused[core], own[core], threshold, out=out[core])
            # a pixel without history (reset, or max_history 1) has nothing to sharpen with
            np.copyto(out[core], fused[core], where=reset[core] if floor_weight < 1 else True)

    moving = sum(run(test, strips))
    if moving > config.global_motion * motion.size:
        # the camera moved: what was not flagged moved below the noise; every pixel
        # restarts from this frame, as a stream's first frame does
        fresh = start(frame)
        motion[:] = True
        if inconsistency is not None:
            image, variance, _ = inconsistency.apply(image, variance)
        return Fused(image, variance, motion, fresh.weight, ratio, fresh)
    reset |= motion
    run(update, strips)
    state = TemporalState(fused, own, weight, bound, frame.censored)
    if inconsistency is not None:  # output only: the history keeps estimates of one kind
        out, fused_var, used = inconsistency.apply(out, fused_var, reset)
        motion = motion | used
    return Fused(out, fused_var, motion, weight, ratio, state)


def _running_mean(mean: np.ndarray, new: np.ndarray, weight: np.ndarray, scale: np.float32 | None,
                  out: np.ndarray) -> None:
    """out = scale mean + weight (new - scale mean), float32; equals ``new`` where weight is 1."""
    if scale is not None:
        mean = mean * scale
    np.subtract(new, mean, out=out)
    out *= weight
    out += mean


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
    diff = own - mean
    weight = diff * diff
    with np.errstate(divide="ignore", invalid="ignore"):
        np.divide(threshold, weight, out=weight)  # inf where own == mean: weight 0 below
    np.subtract(1, weight, out=weight)
    np.maximum(weight, 0, out=weight)
    diff *= weight
    out = np.add(diff, mean, out=out)
    np.maximum(out, 0, out=out)
    return out
