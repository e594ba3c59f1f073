"""The within-frame exposure-consistency test (``integration`` exposure timing).

Where long exposures integrate over a longer time than short ones, a moving
object makes them disagree: the frame's estimate (the stream passes the window
estimate of svelive.reconstruction.numerics.window_estimate, whatever its method,
so that a sharp method's texture is not taken for motion) is compared with the
interpolation of the shortest exposure's uncensored samples alone, by the
noise-model test of svelive.reconstruction.numerics.disagree; flagged
pixels, widened by ``widen`` pixels, take the shortest exposure's estimate,
which integrates over the shortest time. Units: radiance in DN at relative
exposure 1, variances in DN^2 at exposure 1.
"""

from __future__ import annotations

import threading
from concurrent.futures import Executor
from dataclasses import dataclass, field
from functools import cached_property, lru_cache

import numpy as np

from svelive.core.errors import SveliveError
from svelive.core.pattern import Pattern
from svelive.jit import flat, kernel
from svelive.reconstruction.config import MotionConfig
from svelive.reconstruction.methods.base import SveInput, binomial_kernel, map_on, smooth, support_size, tile_rows
from svelive.reconstruction.numerics import STRIP_ROWS, _disagrees, _maximum, _strips, _widen


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
