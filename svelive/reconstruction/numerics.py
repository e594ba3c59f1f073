"""Per-pixel helpers both motion tests share: the estimate they test, the noise-model disagreement test, mask
growth, strips."""

from __future__ import annotations

from concurrent.futures import Executor
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from svelive.core.pattern import Pattern
from svelive.jit import flat, kernel
from svelive.reconstruction.methods.base import (SveInput, map_on, reflect_101, smooth, tile_rows, window_kernels,
                                                 window_level_row)


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


@kernel
def _maximum(a, b):
    """max(a, b) with numpy's NaN propagation from ``a``."""
    return b if a < b else a


# ----- the motion tests' estimate: the same for every method ----------------------------------

@dataclass(frozen=True)
class _WindowLayout:
    """What :func:`window_estimate` needs that the tile alone fixes for frames of one shape, read-only.

    Sums over the tile's window of a frame without censored readings; they repeat with the
    tile's period away from the top and bottom borders, so they are kept for the rows of a
    small frame (methods.base.tile_rows): row r's are ``table[row_of[r]]``.

    Attributes:
        kernels: float32 binomial kernels (rows, cols) of the window, then their squares.
        row_of: intp (H,), the tables' row of each frame row.
        exposure: float32 (n, W), sum G e.
        exposure_squares: float32 (n, W), sum G^2 e.
        squares: float32 (n, W), sum G^2.
    """

    kernels: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
    row_of: np.ndarray
    exposure: np.ndarray
    exposure_squares: np.ndarray
    squares: np.ndarray


@lru_cache(maxsize=8)
def _window_layout(pattern: Pattern, period: tuple[int, int], shape: tuple[int, int]) -> _WindowLayout:
    """The :class:`_WindowLayout` of a nominal tile (``period``: the window's tile) over frames of ``shape``."""
    kernels = window_kernels(period)
    small, row_of = tile_rows(shape[0], int(np.lcm(period[0], pattern.shape[0])), kernels[0].size // 2)
    exposure = pattern.exposure_map((small, shape[1]))
    tables = [smooth(exposure, kernels[0], kernels[1]), smooth(exposure, kernels[2], kernels[3]),
              smooth(np.ones_like(exposure), kernels[2], kernels[3])]
    row_of = row_of.astype(np.intp)
    for array in (row_of, *kernels, *tables):
        array.setflags(write=False)
    return _WindowLayout(kernels, row_of, *tables)


def completed_window(window: tuple[np.ndarray, np.ndarray], image: np.ndarray,
                     variance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A window mean and variance a method made in its own pass (``Estimate.window``), completed as
    :func:`window_estimate` completes its own: the method's ``image`` and ``variance`` where the window
    holds no uncensored reading (an infinite variance). In place; returns the pair."""
    level, noise = window
    lost = np.isinf(noise)
    if lost.any():
        level[lost], noise[lost] = image[lost], variance[lost]
    return level, noise


def window_estimate(inp: SveInput, image: np.ndarray, variance: np.ndarray, workers: int | Executor = 1,
                    strip_rows: int = STRIP_ROWS) -> tuple[np.ndarray, np.ndarray]:
    """The estimate both motion tests compare, and its noise variance: float32 (H, W) each (DN, DN^2).

    The shot-noise maximum-likelihood estimate of the radiance over a binomial window holding
    every phase of the frame's tile (the joint tile of a colour frame), from the uncensored
    readings alone: ``L = sum G s / sum G e``, with variance
    ``(L / g sum G^2 e + sigma^2 sum G^2) / (sum G e)^2`` from the noise model (sensor.py).
    It does not depend on the reconstruction method: a method that keeps each pixel's
    own reading where its neighbours disagree (``adaptive``) gives a sharp estimate whose
    error at texture is mostly bias, the same in every frame of a static scene, and whose
    variance says so; testing that against a history flags only part of a camera pan. A
    window mean's loss of resolution is the same in every frame too, and cancels, while its
    noise is what the model predicts. Where the window holds no uncensored reading (a lower
    bound), the method's ``image`` and ``variance`` are taken.

    Args:
        inp: the prepared frame (per-pixel exposures and folded colour frames too).
        image, variance: float32 (H, W), the method's estimate and variance, used where
            the window holds no uncensored reading.
        workers: threads (or an Executor) over which strips of ``strip_rows`` rows are spread;
            the result depends on neither.

    Cost: with windows of up to :data:`INLINE_TAPS` taps (tiles of up to 4 rows and 2 columns), one
    compiled pass per strip reads the readings, their exposures (a row per tile row unless they
    are per pixel) and censoring once and writes the two results, the window sums made inside
    it, bit-identical to OpenCV's (:func:`_window_strip`); wider tiles' sums along rows are
    OpenCV's (four windows of a row each). Tiles of more rows: a strip without censored
    readings reads the tile's sums of e, G^2 e and G^2, computed once per pattern and frame
    size; a strip with some takes four OpenCV windows over its uncensored readings.
    """
    h, w = inp.shape
    per_pixel = inp.folded or inp.pattern.pixel_map is not None
    layout = None if per_pixel else _window_layout(inp.pattern, inp.period, inp.shape)
    kernels = layout.kernels if layout is not None else window_kernels(inp.period)
    radius = kernels[0].size // 2
    sensor = inp.sensor
    inv_gain, floor = np.float32(1.0 / sensor.effective_gain), np.float32(sensor.floor_variance)
    out, out_var = np.empty((h, w), np.float32), np.empty((h, w), np.float32)
    if kernels[0].size <= INLINE_TAPS[0]:
        # one pass over the readings: each strip's window sums inside the kernel (along rows
        # longer than INLINE_TAPS[1], OpenCV's sums of the strip's rows)
        period = h if per_pixel else min(inp.pattern.shape[0], h)
        exposure = inp.exposure[:period]
        along = None if kernels[1].size <= INLINE_TAPS[1] else kernels[1::2]
        no_rows = np.empty((4, 0, w), np.float32)

        def inline(core: slice) -> None:
            rows = no_rows if along is None else _row_sums(inp, slice(max(core.start - radius, 0),
                                                                      min(core.stop + radius, h)), *along)
            _window_strip(inp.signal, exposure, inp.censored, core.start, core.stop, *kernels, inv_gain, floor,
                          image, variance, out, out_var, rows)

        map_on(workers, inline, _strips(h, strip_rows))
        return out, out_var

    def strip(core: slice) -> None:
        ext = slice(max(core.start - radius, 0), min(core.stop + radius, h))
        keep = slice(core.start - ext.start, core.stop - ext.start)
        ky, kx, ky2, kx2 = kernels
        censored = inp.censored[ext]
        if layout is not None and not censored.any():  # the tile's sums of e, G^2 e and G^2 hold
            summed = smooth(inp.signal[ext], ky, kx)[keep]
            tables = layout.exposure, layout.exposure_squares, layout.squares
            row_of, first = layout.row_of, core.start
        else:  # the sums over uncensored readings only: four windows of the strip
            kept = np.empty(censored.shape, np.float32)
            signal, exposure = np.empty_like(kept), np.empty_like(kept)
            _uncensored(*flat(np.ascontiguousarray(inp.signal[ext]), np.ascontiguousarray(inp.exposure[ext]),
                              np.ascontiguousarray(censored), kept, signal, exposure))
            summed = smooth(signal, ky, kx)[keep]
            tables = (smooth(exposure, ky, kx)[keep], smooth(exposure, ky2, kx2)[keep], smooth(kept, ky2, kx2)[keep])
            row_of, first = np.arange(core.stop - core.start, dtype=np.intp), 0  # the strip's own rows
        lost = _window_rows(np.ascontiguousarray(summed), row_of, first, *tables, out[core], out_var[core],
                            inv_gain, floor)
        if lost:  # windows without an uncensored reading (rare): the method's bound and variance
            where = np.isinf(out_var[core])
            out[core][where], out_var[core][where] = image[core][where], variance[core][where]

    map_on(workers, strip, _strips(h, strip_rows))
    return out, out_var


@kernel
def _uncensored(signal, exposure, censored, kept, kept_signal, kept_exposure):
    """kept = 1 at uncensored readings, 0 at censored ones; s and e times it (flat arrays)."""
    zero, one = np.float32(0), np.float32(1)
    for k in range(signal.size):
        u = zero if censored[k] else one
        kept[k] = u
        kept_signal[k] = signal[k] * u
        kept_exposure[k] = exposure[k] * u


@kernel
def _window_rows(summed, row_of, first, exposure, exposure_squares, squares, out, out_var, inv_gain, floor):
    """out = max(sum G s / sum G e, 0) and its variance, (R, W) rows whose window sums of e, G^2 e
    and G^2 are the tables' rows ``row_of[first + r]``; 0 and an infinite variance where the
    window's sum G e is 0 (no uncensored reading), whose count it returns."""
    lost = 0
    for r in range(out.shape[0]):
        t = row_of[first + r]
        lost += window_level_row(summed[r], exposure[t], exposure_squares[t], squares[t], inv_gain, floor, out[r],
                                 out_var[r])
    return lost


#: The longest windows (rows, columns) :func:`window_estimate` sums inside its kernel, in the order
#: of OpenCV's sums, which :func:`_symmetric_row` repeats for these lengths only (tested; OpenCV
#: sums a row of 5 taps otherwise): longer rows take OpenCV's sums along them, more rows OpenCV's
#: windows.
INLINE_TAPS = (5, 3)


def _row_sums(inp: SveInput, rows: slice, kernel: np.ndarray, squares: np.ndarray) -> np.ndarray:
    """float32 (4, R, W): the ``rows`` of the frame's uncensored s, e, e and 1 (0 where censored)
    each summed along its row (OpenCV, ends mirrored), with ``kernel``, ``kernel``, ``squares``
    and ``squares`` (:func:`_window_strip`'s rows)."""
    one = np.ones(1, np.float32)
    kept = np.logical_not(inp.censored[rows]).astype(np.float32)
    signal, exposure = inp.signal[rows] * kept, inp.exposure[rows] * kept
    return np.stack([smooth(signal, one, kernel), smooth(exposure, one, kernel), smooth(exposure, one, squares),
                     smooth(kept, one, squares)])


@kernel
def _symmetric_row(x, k, out):
    """out = x (1-D) filtered with the symmetric kernel ``k`` (odd length), ends mirrored
    (BORDER_REFLECT_101), summed in the order OpenCV sums rows of up to 3 taps and columns of up
    to 5 (:data:`INLINE_TAPS`): the centre tap, then each pair of taps added before its weight is
    applied, so the result is bit-identical to methods.base.smooth's."""
    n, a = x.size, k.size // 2
    centre = k[a]
    for c in range(n):
        out[c] = x[c] * centre
    for j in range(1, a + 1):
        kj = k[a + j]
        inner = n - 2 * j
        if inner > 0:  # slices, so that LLVM vectorises the loop
            left, right, middle = x[:inner], x[2 * j:], out[j:n - j]
            for c in range(inner):
                middle[c] = middle[c] + (left[c] + right[c]) * kj
        for c in range(min(j, n)):
            out[c] = out[c] + (x[reflect_101(c - j, n)] + x[reflect_101(c + j, n)]) * kj
        for c in range(max(n - j, j), n):
            out[c] = out[c] + (x[reflect_101(c - j, n)] + x[reflect_101(c + j, n)]) * kj


@kernel
def _symmetric_column(ring, q, slots, k, out):
    """out = the rows ``ring[q, slots[0..]]`` (the window's rows, top to bottom) combined with the
    symmetric kernel ``k`` in :func:`_symmetric_row`'s order."""
    a = k.size // 2
    centre = ring[q, slots[a]]
    kc = k[a]
    for c in range(out.size):
        out[c] = centre[c] * kc
    for j in range(1, a + 1):
        above, below = ring[q, slots[a - j]], ring[q, slots[a + j]]
        kj = k[a + j]
        for c in range(out.size):
            out[c] = out[c] + (above[c] + below[c]) * kj


@kernel
def _kept_row_sums(e_row, s_row, c_row, kx, kx2, kept, kept_signal, kept_exposure, ring, slot):
    """One row's sums along it over its uncensored readings (exposures ``e_row``, readings ``s_row``, censored
    ``c_row``): of s and e with ``kx``, of e and 1 with ``kx2``, into ``ring[0..3, slot]`` (:func:`_window_strip`'s
    ring); ``kept``, ``kept_signal``, ``kept_exposure``: (W,) scratch."""
    _uncensored(s_row, e_row, c_row, kept, kept_signal, kept_exposure)
    _symmetric_row(kept_signal, kx, ring[0, slot])
    _symmetric_row(kept_exposure, kx, ring[1, slot])
    _symmetric_row(kept_exposure, kx2, ring[2, slot])
    _symmetric_row(kept, kx2, ring[3, slot])


@kernel
def _window_strip(signal, exposure, censored, first, stop, ky, kx, ky2, kx2, inv_gain, floor, image, variance,
                  out, out_var, row_sums):
    """:func:`window_estimate` of rows ``first:stop`` of the (H, W) frame (``exposure``: (P, W), row r's
    exposures are row r % P), written to those rows of ``out`` and ``out_var``.

    Each row of the window is summed along once (s, e and 1 over the uncensored readings, with
    the kernels and their squares) into a ring of the window's rows, which are then summed down;
    rows beyond the frame mirror (BORDER_REFLECT_101). Sums, estimate and variance are
    bit-identical to the four OpenCV windows of the readings and :func:`_window_rows`: the method's
    ``image`` and ``variance`` where the window holds no uncensored reading. ``row_sums``: the
    sums along the frame's rows max(first - a, 0) on (a: the window's rows // 2), as
    :func:`_row_sums` makes them, or (4, 0, W) to make them here.
    """
    if ky.size == 5 and kx.size == 1 and not row_sums.shape[1]:
        _window_strip_column(signal, exposure, censored, first, stop, ky, kx, ky2, kx2, inv_gain, floor, image,
                             variance, out, out_var)
        return
    rows, cols = signal.shape
    period = exposure.shape[0]
    size = ky.size
    a = size // 2
    ring = np.empty((4, size, cols), np.float32)  # per window row: sum G s, sum G e, sum G^2 e, sum G^2
    kept, kept_signal, kept_exposure = (np.empty(cols, np.float32), np.empty(cols, np.float32),
                                        np.empty(cols, np.float32))
    sums = np.empty((4, cols), np.float32)
    slots = np.empty(size, np.intp)
    following = first - a  # the next window row to sum along
    for r in range(first, stop):
        while following <= r + a:
            src = reflect_101(following, rows)
            slot = (following - first + a) % size
            following += 1
            if row_sums.shape[1]:
                for q in range(4):
                    ring[q, slot] = row_sums[q, src - max(first - a, 0)]
                continue
            _kept_row_sums(exposure[src % period], signal[src], censored[src], kx, kx2, kept, kept_signal,
                           kept_exposure, ring, slot)
        for j in range(size):
            slots[j] = (r - a + j - first + a) % size
        _symmetric_column(ring, 0, slots, ky, sums[0])
        _symmetric_column(ring, 1, slots, ky, sums[1])
        _symmetric_column(ring, 2, slots, ky2, sums[2])
        _symmetric_column(ring, 3, slots, ky2, sums[3])
        level_row, noise_row = out[r], out_var[r]
        lost = window_level_row(sums[0], sums[1], sums[2], sums[3], inv_gain, floor, level_row, noise_row)
        for c in range(cols if lost else 0):
            if np.isinf(noise_row[c]):
                level_row[c], noise_row[c] = image[r, c], variance[r, c]


@kernel
def _window_strip_column(signal, exposure, censored, first, stop, ky, kx, ky2, kx2, inv_gain, floor, image, variance,
                         out, out_var):
    """:func:`_window_strip` of a window 5 rows tall and 1 column wide (tiles of 4 rows and 1 column: dual-ISO,
    whose motion window is 5x1), bit for bit: each pixel's four window sums made in one loop from its 5 rows'
    readings, each term the ring's value (uncensored s, e, e, 1 times the one tap along the row) and summed down
    in :func:`_symmetric_column`'s order, instead of the ring's row sums written and summed down in a dozen passes
    over the row (x0.3-0.4 of the time)."""
    rows, cols = signal.shape
    period = exposure.shape[0]
    zero, one = np.float32(0), np.float32(1)
    g, g2 = kx[0], kx2[0]
    k0, k1, k2 = ky[2], ky[3], ky[4]
    q0, q1, q2 = ky2[2], ky2[3], ky2[4]
    sums = np.empty((4, cols), np.float32)
    gs, ge, ge2, gg = sums[0], sums[1], sums[2], sums[3]
    for r in range(first, stop):
        i0, i1, i3, i4 = reflect_101(r - 2, rows), reflect_101(r - 1, rows), reflect_101(r + 1, rows), \
            reflect_101(r + 2, rows)
        s0, s1, s2, s3, s4 = signal[i0], signal[i1], signal[r], signal[i3], signal[i4]
        e0, e1, e2, e3, e4 = (exposure[i0 % period], exposure[i1 % period], exposure[r % period],
                              exposure[i3 % period], exposure[i4 % period])
        c0, c1, c2, c3, c4 = censored[i0], censored[i1], censored[r], censored[i3], censored[i4]
        for x in range(cols):
            u0, u1, u2 = zero if c0[x] else one, zero if c1[x] else one, zero if c2[x] else one
            u3, u4 = zero if c3[x] else one, zero if c4[x] else one
            a0, a1, a2, a3, a4 = e0[x] * u0, e1[x] * u1, e2[x] * u2, e3[x] * u3, e4[x] * u4
            gs[x] = ((s2[x] * u2 * g) * k0 + ((s1[x] * u1) * g + (s3[x] * u3) * g) * k1
                     + ((s0[x] * u0) * g + (s4[x] * u4) * g) * k2)
            ge[x] = (a2 * g) * k0 + (a1 * g + a3 * g) * k1 + (a0 * g + a4 * g) * k2
            ge2[x] = (a2 * g2) * q0 + (a1 * g2 + a3 * g2) * q1 + (a0 * g2 + a4 * g2) * q2
            gg[x] = (u2 * g2) * q0 + (u1 * g2 + u3 * g2) * q1 + (u0 * g2 + u4 * g2) * q2
        level_row, noise_row = out[r], out_var[r]
        lost = window_level_row(gs, ge, ge2, gg, inv_gain, floor, level_row, noise_row)
        for c in range(cols if lost else 0):
            if np.isinf(noise_row[c]):
                level_row[c], noise_row[c] = image[r, c], variance[r, c]
