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
from dataclasses import dataclass, field
from functools import cached_property, lru_cache

import cv2
import numpy as np

from svelive.errors import SveliveError
from svelive.jit import flat, kernel
from svelive.methods.base import SveInput, binomial_kernel, map_on, smooth, support_size, tile_rows
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
    """bool: ``(a - b)^2 > sigmas^2 (var_a + var_b)``, the noise-model test of two float32 estimates (broadcast)."""
    arrays = [np.ascontiguousarray(x, np.float32) for x in np.broadcast_arrays(a, var_a, b, var_b)]
    out = np.empty(arrays[0].shape, bool)
    _disagree_pass(*flat(*arrays, out), np.float32(sigmas * sigmas))
    return out


@kernel
def _disagrees(a, var_a, b, var_b, k2):
    """:func:`disagree` of one pixel, k2 = sigmas^2 (float32)."""
    diff = a - b
    return diff * diff > (var_a + var_b) * k2


@kernel
def _disagree_pass(a, var_a, b, var_b, out, k2):
    for k in range(a.size):
        out[k] = _disagrees(a[k], var_a[k], b[k], var_b[k], k2)


#: Rows per strip of the per-pixel passes: small enough for a strip's arrays to stay in cache
#: from its test to its update.
STRIP_ROWS = 64


def _strips(height: int, rows: int) -> list[slice]:
    """The frame's rows in strips of ``rows`` (the last one shorter)."""
    rows = max(1, int(rows))
    return [slice(top, min(top + rows, height)) for top in range(0, height, rows)]


# ----- within one frame -----------------------------------------------------

def _window_kernels(pattern: Pattern) -> tuple[np.ndarray, np.ndarray]:
    """The binomial (rows, columns) kernels of a window holding every phase of the tile."""
    th, tw = pattern.shape
    return binomial_kernel(support_size(th)), binomial_kernel(support_size(tw))


@dataclass(frozen=True)
class _ShortestLayout:
    """What the shortest exposure's interpolation needs that depends only on (pattern, shape), read-only.

    The tables hold a frame's window sums when none of the level's samples is
    censored; a window's sums repeat with the tile's period away from the top and
    bottom borders, so they are kept for the rows of a small frame
    (methods.base.tile_rows): row r's are ``table[row_of[r]]``.

    Attributes:
        exposure: the level's relative exposure e.
        mask: float32 (P, W), 1 at the level's pixels, by row phase: pixel (r, c) is ``mask[r % P, c]``.
        kernels: float32 binomial kernels (rows, cols) of the window, then their squares.
        row_of: intp (H,), the tables' row of each frame row.
        scale: float32 (n, W), the window's sum of weights times e.
        denominator: float32 (n, W), ``max(effective, 1e-6) e^2``, effective = (sum w)^2 / sum w^2
            the window's effective number of samples.
        valid: bool (n, W), the window's sum of weights exceeds 1e-6.
    """

    exposure: float
    mask: np.ndarray
    kernels: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
    row_of: np.ndarray
    scale: np.ndarray
    denominator: np.ndarray
    valid: np.ndarray


@lru_cache(maxsize=8)
def _shortest_layout(pattern: Pattern, shape: tuple[int, int]) -> _ShortestLayout:
    """The :class:`_ShortestLayout` of a nominal tile over frames of ``shape``."""
    exposure = float(pattern.levels[0])
    ky, kx = _window_kernels(pattern)
    kernels = (ky, kx, ky * ky, kx * kx)
    small, row_of = tile_rows(shape[0], pattern.shape[0], ky.size // 2)
    mask = (pattern.level_index_map((small, shape[1])) == 0).astype(np.float32)
    tables = _window_tables(smooth(mask, ky, kx), smooth(mask, kernels[2], kernels[3]), exposure)
    mask = np.ascontiguousarray(mask[:min(pattern.shape[0], small)])
    row_of = row_of.astype(np.intp)
    for array in (mask, row_of, *kernels, *tables):
        array.setflags(write=False)
    return _ShortestLayout(exposure, mask, kernels, row_of, *tables)


def _window_tables(weight_sum: np.ndarray, squares: np.ndarray, exposure: float) -> list[np.ndarray]:
    """[scale, denominator, valid] of :class:`_ShortestLayout` from the window sums of the weights and their squares."""
    scale, denominator = np.empty_like(weight_sum), np.empty_like(weight_sum)
    valid = np.empty(weight_sum.shape, bool)
    _tables_pass(*flat(weight_sum, squares, scale, denominator, valid), np.float32(exposure),
                 np.float32(exposure * exposure))
    return [scale, denominator, valid]


@kernel
def _tables_pass(weight_sum, squares, scale, denominator, valid, exposure, exposure2):
    for k in range(weight_sum.size):
        total = weight_sum[k]
        valid[k] = total > np.float32(1e-6)
        scale[k] = total * exposure
        effective = total * total / _maximum(squares[k], np.float32(1e-12))
        denominator[k] = _maximum(effective, np.float32(1e-6)) * exposure2


@dataclass(frozen=True)
class _ShortNoise:
    """What the shortest exposure's variance is computed from: (estimate slope + floor) / denominator.

    Attributes:
        slope, floor: float32, the noise model's variance of one reading over e^2, ``slope * L + floor`` at radiance L.
        layout: the tables of frames without censored samples of the level.
        own: for each strip where the level had censored samples, (rows, row_of, first, denominator,
            valid): its frame rows and its own tables, row r of ``rows`` at ``row_of[first + r]``.
    """

    slope: np.float32
    floor: np.float32
    layout: _ShortestLayout
    own: list[tuple[slice, np.ndarray, int, np.ndarray, np.ndarray]] = field(default_factory=list)


class Inconsistency:
    """The within-frame test's finding: where to rely on the shortest exposure, and its estimate.

    Made by :func:`exposure_consistency`, and computed by strips when needed:
    :func:`fuse` tests each strip just before it updates it, while the strip's rows
    are in cache, and keeps the strip's estimate only as long as it uses it;
    reading ``flagged`` tests the rows still untested, reading ``image`` (or
    ``variance``) tests again the rows whose estimate was not kept (so until then
    it holds on to the frame's arrays). Results do not depend on the order or the
    strips.

    Attributes:
        flagged: bool (H, W), widened pixels whose estimate disagrees with the shortest exposure's.
        image: float32 (H, W), the shortest exposure's estimate.
        variance: float32 (H, W), its variance (inf where its window holds no uncensored
            sample), computed on first access: the live path only reads it through
            :class:`OutputVariance`.
    """

    def __init__(self, image: np.ndarray, variance: np.ndarray, inp: SveInput, config: MotionConfig,
                 workers: int | Executor = 1, strip_rows: int = STRIP_ROWS) -> None:
        if inp.pattern.pixel_map is not None:
            raise SveliveError("the exposure-consistency test needs a nominal tile, not a per-pixel exposure map")
        layout = _shortest_layout(inp.pattern, inp.shape)
        sensor = inp.sensor
        self._frame: tuple | None = (image, variance, inp)
        self._noise = _ShortNoise(np.float32(layout.exposure / sensor.effective_gain),
                                  np.float32(sensor.floor_variance), layout)
        self._k2 = np.float32(config.consistency_sigmas * config.consistency_sigmas)
        self._widen = int(config.widen)
        self._flagged = np.empty(inp.shape, bool)
        self._image: np.ndarray | None = None  # made when the estimate is first kept
        self._tested, self._kept = np.zeros(inp.shape[0], bool), np.zeros(inp.shape[0], bool)  # by row
        self._lock = threading.Lock()
        self._workers, self._strip_rows = workers, strip_rows

    def test(self, rows: slice, short: np.ndarray) -> None:
        """Test the frame rows ``rows``, writing their estimate to ``short`` (float32 (len(rows), W));
        threads may test disjoint rows at once."""
        if self._kept[rows].all():  # (then the frame's arrays may be gone)
            short[...] = self._image[rows]
            return
        _consistency_rows(rows, *self._frame, self._noise.layout, self._noise.slope, self._noise.floor, self._k2,
                          self._widen, self._flagged, short)
        self._tested[rows] = True

    def _keep(self, rows: slice) -> None:
        """Test ``rows`` keeping their estimate, and the tables of its variance."""
        own = _consistency_rows(rows, *self._frame, self._noise.layout, self._noise.slope, self._noise.floor,
                                self._k2, self._widen, self._flagged, self._image[rows])
        if own is not None:
            self._noise.own.append(own)
        self._tested[rows] = self._kept[rows] = True

    def _completed(self, keep: bool) -> Inconsistency:
        """Self, with every row tested and, with ``keep``, every estimate kept."""
        done = self._kept if keep else self._tested
        if not done.all():
            with self._lock:
                if self._image is None:
                    self._image = np.empty(self._flagged.shape, np.float32)
                strips = [s for s in _strips(len(done), self._strip_rows) if not done[s].all()]
                map_on(self._workers, self._keep, strips)
                if self._kept.all():  # the frame's arrays are not needed any more: do not keep them alive
                    self._frame = None
        return self

    @property
    def flagged(self) -> np.ndarray:
        return self._completed(False)._flagged

    @property
    def image(self) -> np.ndarray:
        return self._completed(True)._image

    @cached_property
    def variance(self) -> np.ndarray:
        """float32 (H, W), DN^2: the variance of ``image``."""
        short, noise = self.image, self._noise
        layout = noise.layout
        variance = np.empty(short.shape, np.float32)
        _variance_rows(short, layout.row_of, 0, layout.denominator, layout.valid, noise.slope, noise.floor, variance)
        for rows, row_of, first, denominator, valid in noise.own:
            _variance_rows(short[rows], row_of, first, denominator, valid, noise.slope, noise.floor, variance[rows])
        return variance

    def apply(self, image: np.ndarray) -> np.ndarray:
        """A new float32 (H, W) array: the shortest exposure's estimate where flagged, ``image`` elsewhere
        (the variance is :class:`OutputVariance`'s, on demand)."""
        out = np.empty(image.shape, np.float32)
        _select_pass(*flat(self.flagged, self.image, np.ascontiguousarray(image, np.float32), out))
        return out


@kernel
def _select_pass(flagged, replacement, image, out):
    # every value is loaded before the choice: a load under a condition keeps LLVM from
    # vectorising a loop (2-3x slower; so in the other kernels that choose)
    for k in range(out.size):
        use, a, b = flagged[k], replacement[k], image[k]
        out[k] = a if use else b


def exposure_consistency(image: np.ndarray, variance: np.ndarray, inp: SveInput, config: MotionConfig,
                         workers: int = 1, strip_rows: int = STRIP_ROWS,
                         executor: Executor | None = None) -> Inconsistency:
    """Within-frame test: where does the frame's estimate disagree with the shortest exposure's beyond noise?

    The shortest exposure's estimate interpolates its uncensored samples alone,
    as the ``weighted`` method interpolates one level: a binomial window holding
    every phase of the tile averages the readings s / e, and the variance is the
    noise model's at that radiance divided by the window's effective number of
    samples (sum w)^2 / sum w^2. Where the two estimates differ by more than
    ``config.consistency_sigmas`` (:func:`disagree`), pixels are flagged; flags
    widen by ``config.widen`` pixels, and stay only where the window held a sample.

    The estimates interpolate different pixels, so at static fine texture they
    also disagree (spatial aliasing, not in the noise model): a caller with a
    history applies the finding only where the temporal test saw motion.

    Args:
        image, variance: float32 (H, W), a single-frame estimate and its variance (DN, DN^2),
            not modified while the finding is in use.
        inp: the prepared raw frame it came from (a nominal tile, no per-pixel exposure map).
        workers, executor: threads over which strips of ``strip_rows`` rows are spread when
            the finding is completed (:func:`fuse`); the result depends on none of them.

    Returns:
        the finding, computed when used (:class:`Inconsistency`).
    """
    return Inconsistency(image, variance, inp, config, executor if executor is not None else workers, strip_rows)


def _consistency_rows(core: slice, image: np.ndarray, variance: np.ndarray, inp: SveInput, layout: _ShortestLayout,
                      slope: np.float32, floor: np.float32, k2: np.float32, widen: int, flagged: np.ndarray,
                      short: np.ndarray) -> tuple | None:
    """:func:`exposure_consistency` of the rows ``core``: writes ``flagged[core]`` and their estimate
    to ``short`` ((len(core), W)). Returns, where the level had censored samples in the strip, the
    strip's own tables (an entry of ``_ShortNoise.own``), else None.

    The test runs on ``widen`` rows more each side (for the widening), whose window
    sums need the window's radius more (both within the frame).
    """
    h, w = inp.shape
    ky, kx, ky2, kx2 = layout.kernels
    mid = slice(max(core.start - widen, 0), min(core.stop + widen, h))
    ext = slice(max(mid.start - ky.size // 2, 0), min(mid.stop + ky.size // 2, h))
    mid_in_ext = slice(mid.start - ext.start, mid.stop - ext.start)
    core_in_mid = slice(core.start - mid.start, core.stop - mid.start)
    product = np.empty((ext.stop - ext.start, w), np.float32)
    no_weights = np.zeros((0, 0), np.float32)
    censored = _shortest_samples(inp.signal[ext], inp.censored[ext], layout.mask, ext.start, product, no_weights)
    summed = smooth(product, ky, kx)[mid_in_ext]
    row_of, first, scale, denominator, valid = layout.row_of, mid.start, layout.scale, layout.denominator, layout.valid
    own = None
    if censored:  # the layout's tables do not hold: the strip's own
        weights = np.empty_like(product)
        _shortest_samples(inp.signal[ext], inp.censored[ext], layout.mask, ext.start, product, weights)
        sums = smooth(weights, ky, kx)[mid_in_ext], smooth(weights, ky2, kx2)[mid_in_ext]
        scale, denominator, valid = _window_tables(*sums, layout.exposure)
        row_of, first = np.arange(mid.stop - mid.start, dtype=np.intp), 0
        for array in (row_of, scale, denominator, valid):  # read-only as the layout's: the kernels' types match
            array.setflags(write=False)
        own = (core, row_of, core_in_mid.start, denominator, valid)
    tested = flagged[core] if widen <= 0 else np.empty(summed.shape, bool)
    count = _shortest_test(summed, row_of, first, scale, denominator, valid, image[mid], variance[mid],
                           slope, floor, k2, tested, short, core_in_mid.start)
    if widen > 0 and count == 0:
        flagged[core] = False
    elif widen > 0:
        _valid_only(_widen(tested, widen)[core_in_mid], row_of, first + core_in_mid.start, valid, flagged[core])
    return own


@kernel
def _shortest_samples(signal, censored, mask, first_row, product, weights):
    """Weights w of the shortest exposure's uncensored samples (written unless ``weights`` is
    empty) and s w, for (R, W) rows from ``first_row`` on (``mask`` by row phase); returns the
    count of the level's censored samples."""
    period = mask.shape[0]
    zero = np.float32(0)
    with_weights = weights.size > 0
    count = 0
    for r in range(signal.shape[0]):
        p = (first_row + r) % period
        for c in range(signal.shape[1]):
            m = mask[p, c]
            lost = censored[r, c]
            weight = zero if lost else m
            product[r, c] = signal[r, c] * weight
            if with_weights:
                weights[r, c] = weight
            count += lost & (m != zero)
    return count


@kernel
def _short_variance(estimate, slope, floor, denominator, valid):
    """The shortest exposure's variance at one pixel (inf where its window holds no sample)."""
    return (estimate * slope + floor) / denominator if valid else np.float32(np.inf)


@kernel
def _shortest_test(summed, row_of, first, scale, denominator, valid, image, variance, slope, floor, k2,
                   flagged, short, core_first):
    """The shortest exposure's estimate and the test of (R, W) rows: ``summed`` the window sums of s w,
    tables (:class:`_ShortestLayout`) at rows ``row_of[first + r]``. Writes ``flagged`` for every row,
    the estimate for rows ``core_first:core_first + len(short)``; returns the count flagged."""
    zero = np.float32(0)
    count = 0
    for r in range(summed.shape[0]):
        t = row_of[first + r]
        core = core_first <= r < core_first + short.shape[0]
        for c in range(summed.shape[1]):
            ok, total, weight_sum = valid[t, c], summed[r, c], scale[t, c]
            estimate = _maximum(total / weight_sum if ok else total, zero)
            var = _short_variance(estimate, slope, floor, denominator[t, c], ok)
            f = ok & _disagrees(image[r, c], variance[r, c], estimate, var, k2)
            flagged[r, c] = f
            count += f
            if core:
                short[r - core_first, c] = estimate
    return count


@kernel
def _variance_rows(short, row_of, first, denominator, valid, slope, floor, out):
    """out = the variance of the shortest exposure's estimate ``short``, (R, W) rows whose tables'
    rows are ``row_of[first + r]``."""
    for r in range(short.shape[0]):
        t = row_of[first + r]
        for c in range(short.shape[1]):
            out[r, c] = _short_variance(short[r, c], slope, floor, denominator[t, c], valid[t, c])


@kernel
def _valid_only(grown, row_of, first, valid, out):
    """out = grown where the window held a sample (``valid`` at table rows ``row_of[first + r]``)."""
    for r in range(grown.shape[0]):
        t = row_of[first + r]
        for c in range(grown.shape[1]):
            out[r, c] = grown[r, c] & valid[t, c]


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
    within-frame test of a strip's rows (``inconsistency``, computed on demand)
    runs just before its temporal test. The global brightness ratio is measured
    first, on a subsample.
    """
    image, variance, bound = frame.image, frame.variance, frame.bound
    if state is None or state.mean.shape != image.shape:
        return _restart(frame, inconsistency, 1.0, np.zeros(image.shape, bool))
    ratio = illumination_ratio(state, image, variance, bound) if config.compensate_illumination else 1.0
    # mean * 1 is exact: one kernel with and without a brightness correction
    scale = np.float32(ratio) if abs(ratio - 1.0) > RATIO_TOLERANCE else np.float32(1)
    h = image.shape[0]
    strips = _strips(h, strip_rows)
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
    # the output differs from the history's mean where sharpened or replaced by the within-frame test
    out = np.empty_like(image) if detail or inconsistency is not None else fused
    floor_weight = np.float32(1.0 / config.max_history)

    def update(core: slice, short: np.ndarray | None) -> None:
        _update_rows(core.start, state.weight[core], motion[core], state.mean[core], state.own[core], image[core],
                     frame.signal[core], frame.censored[core], frame.inverse, frame.own_slope,
                     frame.own_floor, floor_weight, scale, detail, reset[core], weight[core], fused[core], own[core],
                     out[core])
        if inconsistency is not None:  # output only: the history keeps estimates of one kind
            if not detail:
                out[core] = fused[core]
            _replace(*flat(reset[core], inconsistency._flagged[core], short, out[core], motion[core]))

    limit = config.global_motion * motion.size
    lock = threading.Lock()
    moved = [0]  # moving pixels of the strips tested so far

    def strip(core: slice) -> None:
        with lock:
            if moved[0] > limit:  # the frame restarts: nothing to do
                return
        short = None
        if inconsistency is not None:  # while the strip's rows are in cache; the estimate only for the update
            short = np.empty((core.stop - core.start, image.shape[1]), np.float32)
            inconsistency.test(core, short)
        count = test(core)
        with lock:
            moved[0] += count
            restarts = moved[0] > limit
        if not restarts:
            update(core, short)

    map_on(executor if executor is not None else workers, strip, strips)
    if moved[0] > limit:
        # the camera moved: what was not flagged moved below the noise; every pixel
        # restarts from this frame, as a stream's first frame does
        return _restart(frame, inconsistency, ratio, np.ones(image.shape, bool))
    state = TemporalState(fused, own, weight, bound, frame.censored)
    # the update applied the within-frame test's finding to the output where it reset the history
    return Fused(out, motion, weight, ratio, state, OutputVariance(variance, weight, inconsistency, reset))


def _restart(frame: FrameEstimate, inconsistency: Inconsistency | None, ratio: float, motion: np.ndarray) -> Fused:
    """Every pixel restarts from this frame (a stream's first frame, or the camera moved); motion: the mask to report."""
    fresh = start(frame)
    image = frame.image
    if inconsistency is not None:
        image = inconsistency.apply(image)
        motion = motion | inconsistency.flagged
    return Fused(image, motion, fresh.weight, ratio, fresh, OutputVariance(frame.variance, None, inconsistency))


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
