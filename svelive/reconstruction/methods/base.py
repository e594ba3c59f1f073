"""What every reconstruction method receives and returns.

A method is a function ``run(inp: SveInput, **options) -> Estimate``.
:func:`svelive.reconstruction.input.prepare` makes the SveInput (response
applied, black level removed, exposures, censoring, colour channels) once, from
the frame's camera, so methods only do the reconstruction itself.
"""

from __future__ import annotations

from concurrent.futures import Executor, ThreadPoolExecutor
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from svelive.core.cfa import ColourFilter, joint_period
from svelive.core.pattern import Pattern
from svelive.core.sensor import Sensor
from svelive.jit import kernel


@dataclass(frozen=True)
class SveInput:
    """A raw SVE frame ready for reconstruction.

    Attributes:
        signal: float32 (H, W), raw minus black level, DN (may be slightly negative from noise).
        exposure: float32 (H, W), relative exposure of every pixel (read-only).
        censored: bool (H, W), readings at or above the sensor's censor level: they
            only say "radiance at least signal / exposure".
        pattern: the exposure pattern.
        sensor: the sensor, with its noise model.
        integral: True when every signal value is an integer (integer raw, integer black level).
        cfa: the colour filter layout, or None for a monochrome frame.
        channels: uint8 (H, W), the colour channel (0 R, 1 G, 2 B) of every pixel, or None.
        folded: ``exposure`` is not the pattern's (tile or calibrated map) but each
            pixel's exposure times its colour channel's local share of luminance
            (svelive.reconstruction.colour): a monochrome problem whose exposures vary
            from pixel to pixel off the pattern's levels. Methods then use ``exposure``
            itself wherever they would use what the tile alone fixes, and each censored
            pixel's own bound; ``pattern`` still gives the layout (windows, levels).
    """

    signal: np.ndarray
    exposure: np.ndarray
    censored: np.ndarray
    pattern: Pattern
    sensor: Sensor
    integral: bool = False
    cfa: ColourFilter | None = None
    channels: np.ndarray | None = None
    folded: bool = False

    @property
    def shape(self) -> tuple[int, int]:
        return self.signal.shape  # type: ignore[return-value]

    @property
    def period(self) -> tuple[int, int]:
        """The joint tile of exposure pattern and colour filter (rows, cols)."""
        return self.pattern.shape if self.cfa is None else joint_period(self.pattern.shape, self.cfa.shape)

    def crop(self, rows: slice, cols: slice = slice(None)) -> SveInput:
        """The input of a rectangle of the frame (views, no copies). Keep tile phases in mind: the
        pattern's origin stays the frame's, so ``rows`` and ``cols`` should start on whole tiles."""
        return SveInput(self.signal[rows, cols], self.exposure[rows, cols], self.censored[rows, cols],
                        self.pattern, self.sensor, self.integral, self.cfa,
                        None if self.channels is None else self.channels[rows, cols], self.folded)


@dataclass(frozen=True)
class Estimate:
    """A method's result.

    Attributes:
        image: float32 (H, W), radiance in DN at exposure 1, finite and >= 0.
        lower_bound: bool (H, W), pixels where every sample the method used was
            censored, so ``image`` is only the lower bound they imply.
        variance: float32 (H, W) or None, the method's own predicted variance of
            ``image`` (DN^2 at exposure 1) where it has one.

        window: (level, variance), float32 (H, W) each, or None: the motion tests' window mean
            and its noise variance (svelive.reconstruction.numerics.window_estimate), where the
            method made them in its own pass (asked with ``window=True``); the variance is
            infinite where the window holds no uncensored reading (the caller takes the
            method's own estimate there).

    A colour estimate (svelive.reconstruction.colour) has ``image`` (H, W, 3) camera
    RGB, and ``luminance`` (H, W), the quantity ``lower_bound`` and ``variance``
    describe and the motion tests compare.
    """

    image: np.ndarray
    lower_bound: np.ndarray
    variance: np.ndarray | None = None
    luminance: np.ndarray | None = None
    window: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def plane(self) -> np.ndarray:
        """The (H, W) image ``variance`` and ``lower_bound`` refer to: ``luminance`` for colour, else ``image``."""
        return self.image if self.luminance is None else self.luminance


@lru_cache(maxsize=16)
def exposure_maps(pattern: Pattern, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(exposure, 1 / exposure) of every pixel, float32 (H, W), read-only, cached per pattern and shape."""
    exposure = pattern.exposure_map(shape)
    inverse = (1.0 / exposure).astype(np.float32)
    exposure.setflags(write=False)
    inverse.setflags(write=False)
    return exposure, inverse


@lru_cache(maxsize=8)
def binomial_kernel(size: int) -> np.ndarray:
    """Normalised 1-D binomial kernel of ``size`` taps (a discrete Gaussian), float32, read-only."""
    k = np.array([1.0], dtype=np.float64)
    for _ in range(size - 1):
        k = np.convolve(k, [1.0, 1.0])
    k = (k / k.sum()).astype(np.float32)
    k.setflags(write=False)
    return k


def window_kernels(period: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Binomial (rows, cols) kernels of the motion tests' window holding every phase of a ``period`` tile
    (svelive.reconstruction.numerics.window_estimate), then their squares; float32."""
    ky, kx = (binomial_kernel(support_size(n)) for n in period)
    return ky, kx, ky * ky, kx * kx


def support_size(tile_length: int) -> int:
    """Smallest odd, centred window length that holds every phase of a tile of this length."""
    return tile_length + 1 if tile_length % 2 == 0 else tile_length



def tile_rows(height: int, period: int, radius: int) -> tuple[int, np.ndarray]:
    """A small frame whose rows stand for all ``height`` rows of a frame tiled with ``period`` rows.

    Window sums (reaching ``radius`` rows each side, borders mirrored) of
    anything that repeats with the tile are the same on two rows of one tile
    phase away from the top and bottom borders, so they need computing only on
    a frame of the top border's rows, one tile of rows, and the bottom border's
    rows, in the same phase as the full frame's.

    Returns:
        (rows of the small frame, intp (height,): the small frame's row that holds each row's values).
    """
    rows = np.arange(height)
    if height <= 2 * radius + 2 * period:
        return height, rows
    small = 2 * radius + period + (height - 2 * radius - period) % period
    rows[radius:height - radius] = radius + (rows[radius:height - radius] - radius) % period
    rows[height - radius:] -= height - small
    return small, rows

def smooth(image: np.ndarray, kernel_y: np.ndarray, kernel_x: np.ndarray) -> np.ndarray:
    """Separable filtering, float32, borders mirrored (exposure maps mirror with the data)."""
    return cv2.sepFilter2D(image, cv2.CV_32F, kernel_x, kernel_y, borderType=cv2.BORDER_REFLECT_101)


def censored_lower_bound(inp: SveInput, window: tuple[int, int]) -> np.ndarray:
    """Largest lower bound that censored samples within ``window`` (rows, cols) imply, float32 (H, W)."""
    bound = inp.signal / inp.exposure
    bound *= inp.censored
    return cv2.dilate(bound, np.ones(window, np.uint8), borderType=cv2.BORDER_REFLECT_101)



def fill_lower_bounds(inp: SveInput, lower: np.ndarray, window: tuple[int, int], image: np.ndarray,
                      variance: np.ndarray | None = None, rows: slice | None = None) -> None:
    """Set ``image`` to :func:`censored_lower_bound` at the ``lower`` pixels (bool (H, W)), in place.

    ``variance``, if given, becomes bound^2 there: a bound is known to within
    itself (relative error 1). The bound is taken only at the ``lower`` pixels,
    from the censored bounds of the rows their windows reach (:func:`_fill_bounds`),
    so the cost follows the rows holding them; the values are the whole frame's.
    ``rows``: only the lower pixels of these rows (a strip's kept rows), default all.
    """
    first, last, _ = (rows or slice(0, lower.shape[0])).indices(lower.shape[0])
    if not lower[first:last].any():
        return
    _fill_bounds(inp.signal, inp.exposure, inp.censored, lower, window[0] // 2, window[1] // 2, image,
                 np.empty((0, 0), np.float32) if variance is None else variance, first, last)


@kernel
def _fill_bounds(signal, exposure, censored, lower, ry, rx, image, variance, first, last):
    """image = the largest censored bound s / e within (2 ry + 1, 2 rx + 1) around each ``lower`` pixel of (H, W)
    arrays in rows [first, last) (borders reflect-101, as cv2.dilate in :func:`censored_lower_bound`), variance =
    its square (unless ``variance`` is empty). A row with many lower pixels (more than one in 8) takes the bounds
    of its window's rows (each row's once), their maximum over rows, then over columns, as whole-row loops; a row
    with few computes the bounds of its pixels' windows alone (the same expression, :func:`_bound`)."""
    h, width = lower.shape
    bound = np.empty((h, width), np.float32)
    ready = np.zeros(h, np.bool_)
    rows = np.empty(2 * ry + 1, np.int64)
    column_max = np.empty(width, np.float32)
    for r in range(first, last):
        n = count_true(lower[r])
        if n == 0:
            continue
        for dy in range(2 * ry + 1):
            rows[dy] = reflect_101(r + dy - ry, h)
        dense = n * 8 > width
        if dense:
            for rr in rows:
                if not ready[rr]:
                    _bound_row(signal[rr], exposure[rr], censored[rr], bound[rr])
                    ready[rr] = True
            _rows_max(bound, rows, column_max)
        for c in range(width):
            if not lower[r, c]:
                continue
            m = np.float32(-np.inf)
            for dx in range(2 * rx + 1):
                cc = reflect_101(c + dx - rx, width)
                if dense:
                    m = max(m, column_max[cc])
                else:
                    for dy in range(2 * ry + 1):
                        rr = rows[dy]
                        m = max(m, _bound(signal[rr, cc], exposure[rr, cc], censored[rr, cc]))
            image[r, c] = m
            if variance.size:
                variance[r, c] = m * m


@kernel
def _bound(signal, exposure, censored):
    """A reading's censored bound: s / e at a censored reading, 0 elsewhere (s / e times 0, as numpy's product with
    the mask)."""
    return signal / exposure * np.float32(censored)


@kernel
def _bound_row(signal, exposure, censored, bound):
    """bound = :func:`_bound` of a row's readings."""
    for k in range(signal.size):
        bound[k] = _bound(signal[k], exposure[k], censored[k])


@kernel
def _rows_max(values, rows, out):
    """out = the largest of ``values``' rows ``rows``, column by column."""
    copy_row(values[rows[0]], out)
    for i in range(1, rows.size):
        row = values[rows[i]]
        for c in range(out.size):
            out[c] = max(out[c], row[c])


@kernel
def rows_min(values, rows, out):
    """out = the least of ``values``' rows ``rows``, column by column."""
    copy_row(values[rows[0]], out)
    for i in range(1, rows.size):
        row = values[rows[i]]
        for c in range(out.size):
            out[c] = min(out[c], row[c])


@kernel
def window_level_row(summed, exposures, exposure_squares, squares, inv_gain, floor, level, noise):
    """One row of the window mean L = max(sum G s / sum G e, 0) and its noise variance
    (L / g sum G^2 e + sigma^2 sum G^2) / (sum G e)^2 from its window sums over the uncensored readings
    (float32 (W,) each; ``inv_gain`` 1 / g, ``floor`` sigma^2); 0 and an infinite variance where
    sum G e <= 1e-12 (no uncensored reading), whose count it returns. The motion tests' estimate
    (svelive.reconstruction.numerics.window_estimate), also made inside a method's own pass."""
    zero, one, tiny, inf = np.float32(0), np.float32(1), np.float32(1e-12), np.float32(np.inf)
    lost = 0
    for c in range(level.size):
        b, a, e2, g2 = exposures[c], summed[c], exposure_squares[c], squares[c]
        ok = b > tiny
        inverse = one / b
        ratio = a * inverse
        value = zero if ratio < zero else ratio  # numpy's maximum, NaN kept
        variance = (value * inv_gain * e2 + floor * g2) * inverse * inverse
        level[c] = value if ok else zero
        noise[c] = variance if ok else inf
        lost += not ok
    return lost


@kernel
def reflect_101(i, n):
    """Index ``i`` reflected into [0, n) without repeating the edge (OpenCV's BORDER_REFLECT_101)."""
    if n == 1:
        return 0
    while i < 0 or i >= n:
        i = -i if i < 0 else 2 * (n - 1) - i
    return i


@kernel
def reflected_rows(r, h, rows):
    """rows = the rows of the window of ``rows.size`` (odd) rows around row ``r`` of ``h``, reflect-101."""
    ry = rows.size // 2
    for dy in range(rows.size):
        rows[dy] = reflect_101(r + dy - ry, h)


@kernel
def copy_row(source, out):
    """out[:] = source (1-D arrays of one size) in a loop that LLVM vectorises: numba's slice assignment between
    arrays copies one element a step (about 8x slower on a 1920-pixel float32 row)."""
    for c in range(out.size):
        out[c] = source[c]


@kernel
def count_true(flags):
    """How many of the bool array ``flags`` (1-D) are True."""
    n = 0
    for c in range(flags.size):
        n += flags[c]
    return n


@kernel
def true_positions(flags, count, index):
    """The positions of the ``count`` True of the bool array ``flags`` (1-D, C-contiguous), in order, into the front
    of ``index`` (int64): without branches (a position written at every flag, the count advanced by it), or, where
    they are few (one in 16 or fewer), eight flags at a time as a 64-bit word, skipping the words without any."""
    size = flags.size
    n, c = 0, 0
    if count * 16 <= size:
        words = flags[:size // 8 * 8].view(np.uint64)
        for word in range(words.size):
            if words[word] != 0:
                for c in range(8 * word, 8 * word + 8):
                    index[n] = c
                    n += flags[c]
        c = words.size * 8
    for c in range(c, size):
        index[n] = c
        n += flags[c]
    return n


def pad_same_phase(image: np.ndarray, period: tuple[int, int], before: tuple[int, int],
                   after: tuple[int, int]) -> np.ndarray:
    """Pad (H, W) by ``before``/``after`` (rows, cols) with pixels of the same tile phase.

    Row -1 is filled with row ``th - 1``, row H with row ``H - th`` and so on, so a
    window of the tile's size anywhere in the padded image still holds every
    exposure of the tile. Frames smaller than a tile repeat their edge instead.
    """
    h, w = image.shape
    (b0, b1), (a0, a1) = before, after
    rows = _same_phase_index(h, period[0], b0, a0)
    cols = _same_phase_index(w, period[1], b1, a1)
    out = np.empty((h + b0 + a0, w + b1 + a1), image.dtype)
    out[b0:b0 + h, b1:b1 + w] = image
    # A few pad rows and columns: copying them one slice at a time beats fancy indexing.
    for r in (*range(b0), *range(b0 + h, b0 + h + a0)):
        out[r, b1:b1 + w] = image[rows[r]]
    for c in (*range(b1), *range(b1 + w, b1 + w + a1)):
        out[:, c] = out[:, b1 + cols[c]]
    return out


@lru_cache(maxsize=64)
def _same_phase_index(n: int, period: int, before: int, after: int) -> np.ndarray:
    index = np.arange(-before, n + after)
    low = index < 0
    index[low] += period * (-(index[low] // period))
    high = index >= n
    index[high] -= period * ((index[high] - n) // period + 1)
    index = np.clip(index, 0, n - 1)
    index.setflags(write=False)
    return index


def map_on(workers: int | Executor, function, items) -> list:
    """``[function(i) for i in items]``, on threads where ``workers`` asks for them.

    ``workers`` is a thread count (1: the caller's thread; more: a pool made for
    this call) or an Executor the caller keeps for many calls, which a real-time
    stream should do: a pool per frame costs thread start-ups, and new threads
    make the allocator grow new arenas. numpy and OpenCV release the GIL, so
    strips of one frame run in parallel.

    On an Executor, the caller's thread and the pool's threads but one (``_max_workers``
    of a ThreadPoolExecutor; else one thread of the pool) each take the next item
    until none is left (:func:`_take_items`): two hand-offs a call instead of a
    Future per item, whose submits, notifies and results held the GIL for a fifth
    of the live service's GIL time (py-spy --gil, 1920x1200 mono, 19 strips a
    frame), while the items still go to whichever thread is free.
    """
    if isinstance(workers, Executor):
        items = list(items)
        results: list = [None] * len(items)
        order = iter(range(len(items)))  # shared: next() on it is atomic under the GIL
        helpers = [workers.submit(_take_items, function, items, order, results)
                   for _ in range(min(thread_count(workers) - 1, len(items) - 1))]
        try:
            _take_items(function, items, order, results)
        finally:
            # a helper not started yet has nothing left to take (and may wait behind busy threads): cancelled
            started = [helper for helper in helpers if not helper.cancel()]
        for helper in started:
            helper.result()  # a helper's failure is raised
        return results
    if workers > 1:
        with ThreadPoolExecutor(max_workers=workers) as pool:
            return map_on(pool, function, items)
    return [function(i) for i in items]


def thread_count(workers: int | Executor) -> int:
    """The threads :func:`map_on` spreads items over for ``workers`` (an Executor's ``_max_workers``, 2 when it
    does not say)."""
    return getattr(workers, "_max_workers", 2) if isinstance(workers, Executor) else int(workers)


def _take_items(function, items: list, order, results: list) -> None:
    """results[i] = function(items[i]) for each index i taken from the shared iterator ``order`` until it ends."""
    for i in order:
        results[i] = function(items[i])


def in_strips(run, inp: SveInput, halo: int, rows: int = 64, workers: int | Executor = 1, **options) -> Estimate:
    """Run a local method over horizontal strips of the frame and stitch the results.

    ``run`` must only look ``halo`` rows up and down. Strips of a few dozen rows
    keep the method's temporaries in cache and out of the page-fault path of
    large allocations, which makes chains of numpy operations several times
    faster; strips start on whole tiles so the pattern keeps its phase. The
    result equals a whole-frame run. ``workers``: see :func:`map_on`.
    """
    th = inp.period[0]
    h = inp.shape[0]
    halo = -(-halo // th) * th
    rows = max(-(-rows // th) * th, th)
    if h <= rows + 2 * halo or inp.pattern.pixel_map is not None:
        return run(inp, **options)

    def strip(top: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        start, stop = max(top - halo, 0), min(top + rows + halo, h)
        est = run(inp.crop(slice(start, stop)), **options)
        keep = slice(top - start, top - start + min(rows, h - top))
        return est.image[keep], est.lower_bound[keep], None if est.variance is None else est.variance[keep]

    parts = map_on(workers, strip, range(0, h, rows))
    image = np.concatenate([p[0] for p in parts])
    lower = np.concatenate([p[1] for p in parts])
    variance = None if parts[0][2] is None else np.concatenate([p[2] for p in parts])
    return Estimate(image, lower, variance)
