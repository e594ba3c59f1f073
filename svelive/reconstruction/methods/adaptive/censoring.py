"""Censored readings in ``adaptive``: each censored pixel takes the plain mean of the uncensored neighbours consistent
with its bound (at least the bound), by whichever of three ways to the same sums suits the window and the
density of censored pixels (:func:`censored_pixels`)."""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from svelive.core.pattern import Pattern
from svelive.jit import flat, kernel
from svelive.reconstruction.methods.adaptive.parameters import CONSISTENT_SIGMA, DENSE_ROW, TINY
from svelive.reconstruction.methods.adaptive.strip_pass import column_sums
from svelive.reconstruction.methods.base import (SveInput, count_true, reflect_101, reflected_rows, smooth,
                                                 true_positions)

#: Largest window (taps) whose censored pixels are visited one by one (:func:`censored_pixels`): measured, a 3x3
#: window's visits beat the per-level window sums at any share of censored pixels, a 5x3 one's did not.
DIRECT_TAPS = 9


def censored_pixels(inp: SveInput, image: np.ndarray, w: np.ndarray, x: np.ndarray, ky: np.ndarray,
                     kx: np.ndarray, rows: slice | None = None, out: np.ndarray | None = None) -> np.ndarray:
    """Set ``image`` at censored pixels, in place; returns the pixels left as bounds only, bool (H, W).

    ``rows``: the rows whose censored pixels are wanted (a strip's kept rows; their windows read the rows
    around them), default all; ``image`` and the pixels returned are set in those rows alone.
    ``out``: bool (H, W), C-contiguous, into which those pixels are OR-ed (set True, never cleared) and which is
    returned (adaptive's ``lower``: no array of the strip's size made, cleared and OR-ed a strip), or None: a
    new array, False elsewhere.

    A censored pixel takes the plain (equal-weight) window mean of the
    uncensored neighbours consistent with its bound (x_i + 2 sigma_i >= bound),
    and at least the bound. Equal weights, because noise weights at each
    neighbour's own radiance favour the darker neighbours, and next to a
    censored pixel the surviving ones are the darker ones. With no consistent
    neighbour the pixel is returned for the caller to give it the largest bound
    of its window.

    Three ways to the same sums. A folded input (SveInput.folded: a colour frame's
    luminance, whose exposures vary off the levels), and a tile whose window has
    at most DIRECT_TAPS taps, visit each censored pixel's window once, testing
    its neighbours against its own bound censor / e (:func:`_censored_each`):
    the cost follows the number of censored pixels. A 5x3 window computes, at
    each censored pixel, the window sums of its own level's consistent readings
    with OpenCV's arithmetic (:func:`_censored_separable`): the same values as
    the per-level sums below, at a cost that follows the rows holding censored
    pixels. Otherwise (longer windows, and calibrated per-pixel exposure maps,
    tested against the bound of their nominal level) each level with censored
    pixels gets two window sums over the box around them, one window radius
    wider (cut at the frame's edges), so that inside it they equal whole-frame
    sums: the cost follows the levels' boxes.
    """
    f32 = np.float32
    censor = inp.sensor.censor_level
    first, last, _ = (rows or slice(0, inp.shape[0])).indices(inp.shape[0])
    way = censored_way(inp, ky, kx)
    if way == "each":
        bound_only = np.zeros(inp.shape, bool) if out is None else out
        _censored_each(inp.censored, inp.exposure, w, x, image, bound_only, ky, kx, f32(censor), first, last)
        return bound_only
    if way == "separable":  # OpenCV's sums, computed per pixel
        bound_only = np.zeros(inp.shape, bool) if out is None else out
        _censored_separable(inp.censored, inp.exposure, w, x, image, bound_only, ky, kx,
                            *_level_bounds_of(inp.pattern, censor), first, last)
        return bound_only
    levels = inp.pattern.levels.tolist()
    if inp.pattern.pixel_map is None:
        key, values = inp.exposure, np.array(levels, f32)
    else:
        key, values = inp.pattern.level_index_map(inp.shape), np.arange(len(levels), dtype=np.uint8)
    h, width = inp.shape
    ry, rx = len(ky) // 2, len(kx) // 2
    boxes = np.empty((len(levels), 4), np.int64)  # first row, last row, first column, last column
    if len(levels) < 64:
        _level_boxes(*flat(inp.censored, key), values, width, boxes)
    else:  # more levels than bits in a mask: every level's box is the whole frame
        boxes[:] = (0, h - 1, 0, width - 1)
    bound_only = np.zeros(inp.shape, bool) if out is None else out
    for level, value, (top, bottom, left, right) in zip(levels, values, boxes.tolist()):
        if bottom < 0:
            continue  # no censored pixel of this level
        r0, r1, c0, c1 = max(top - ry, 0), min(bottom + ry + 1, h), max(left - rx, 0), min(right + rx + 1, width)
        consistent, consistent_x = np.empty((r1 - r0, c1 - c0), f32), np.empty((r1 - r0, c1 - c0), f32)
        _consistent(*flat(w, x, consistent, consistent_x), width, r0, c0, c1 - c0, f32(censor / level))
        count, sum_x = smooth(consistent, ky, kx), smooth(consistent_x, ky, kx)
        _fill_censored(*flat(inp.censored, key, x, image, bound_only, count, sum_x), width, value, r0, c0, c1 - c0,
                       max(top, first), min(bottom + 1, last), left, right + 1)
    return bound_only


def censored_way(inp: SveInput, ky: np.ndarray, kx: np.ndarray) -> str:
    """Which way :func:`censored_pixels` takes to its sums: "each" (:func:`_censored_each`) and "separable"
    (:func:`_censored_separable`) visit the censored pixels of the rows asked for, reading w and x only within a
    window of them; "levels" (per-level window sums over each level's box) reads w and x on every row."""
    if inp.folded or (inp.pattern.pixel_map is None and ky.size * kx.size <= DIRECT_TAPS):
        return "each"
    if inp.pattern.pixel_map is None and kx.size == 3 and ky.size == 5:
        return "separable"
    return "levels"


@lru_cache(maxsize=16)
def _level_bounds_of(pattern: Pattern, censor: float) -> tuple[np.ndarray, np.ndarray]:
    """The pattern's levels and the bound a censored reading at each implies (censor / level, rounded as the
    per-level sums of :func:`censored_pixels` round it); float32 (K,), read-only."""
    levels = pattern.levels.tolist()
    values, bounds = np.array(levels, np.float32), np.array([censor / level for level in levels], np.float32)
    values.setflags(write=False)
    bounds.setflags(write=False)
    return values, bounds


@kernel
def _censored_each(censored, exposure, w, x, image, bound_only, ky, kx, censor, first, last):
    """At each censored pixel p of (H, W) arrays: image = max(window mean (binomial weights, borders reflect-101
    as the window sums elsewhere) of the readings consistent with p's own bound censor / e_p, x_p); ``bound_only``
    where none is; in rows [first, last). Consistent (:func:`_consistent_row`): w > 0 and x + 2 / sqrt(w) >= bound,
    tested squared.

    Its cost follows the number of censored pixels, not the levels they are at: a row with few of them visits
    each one's window (:func:`_censored_pixel`); a row with many (more than one in DENSE_ROW) sums every
    pixel's window at once, a loop over the row per tap (:func:`_censored_row`), which LLVM vectorises. Both add
    the same terms in the same order.
    """
    h, width = censored.shape
    rx = kx.size // 2
    rows = np.empty(ky.size, np.int64)
    cols = np.empty(kx.size, np.int64)
    count, total, bound = np.empty(width, np.float32), np.empty(width, np.float32), np.empty(width, np.float32)
    for r in range(first, last):
        n = count_true(censored[r])
        if n == 0:
            continue
        reflected_rows(r, h, rows)
        if n * DENSE_ROW > width and width > 2 * rx:
            _censored_row(exposure[r], w, x, rows, ky, kx, censor, count, total, bound)
            for i in range(2 * rx):  # the row's ends: their windows reflect
                c = i if i < rx else width - 2 * rx + i
                for dx in range(kx.size):
                    cols[dx] = reflect_101(c + dx - rx, width)
                count[c], total[c] = _censored_pixel(w, x, rows, cols, ky, kx, bound[c])
            _censored_fill(censored[r], x[r], count, total, image[r], bound_only[r])
            continue
        for c in range(width):
            if not censored[r, c]:
                continue
            for dx in range(kx.size):
                cols[dx] = reflect_101(c + dx - rx, width)
            count_c, total_c = _censored_pixel(w, x, rows, cols, ky, kx, censor / exposure[r, c])
            image[r, c] = max(total_c / max(count_c, np.float32(TINY)), x[r, c])
            if count_c <= np.float32(0.0):
                bound_only[r, c] = True


@kernel
def _censored_fill(censored, x, count, total, image, bound_only):
    """One row of :func:`_censored_each`'s result at its censored pixels from the window sums (vectorised)."""
    zero, tiny = np.float32(0.0), np.float32(TINY)
    for c in range(x.size):
        estimate = max(total[c] / max(count[c], tiny), x[c])
        image[c] = estimate if censored[c] else image[c]
        bound_only[c] |= censored[c] & (count[c] <= zero)


@kernel
def _censored_pixel(w, x, rows, cols, ky, kx, bound):
    """(weight, weighted sum) of the readings consistent with ``bound`` in the window of ``rows`` x ``cols``."""
    zero = np.float32(0.0)
    reach2 = np.float32(CONSISTENT_SIGMA * CONSISTENT_SIGMA)
    count, total = zero, zero
    for dy in range(ky.size):
        wr, xr, gy = w[rows[dy]], x[rows[dy]], ky[dy]
        for dx in range(kx.size):
            wq, xq = wr[cols[dx]], xr[cols[dx]]
            gap = bound - xq
            if wq > zero and (gap <= zero or wq * gap * gap <= reach2):
                g = gy * kx[dx]
                count += g
                total += g * xq
    return count, total


@kernel
def _censored_row(exposure, w, x, rows, ky, kx, censor, count, total, bound):
    """:func:`_censored_pixel` of every pixel of a row (``exposure`` its exposures) away from its ends, censored
    or not, into ``count`` and ``total``; the window's rows are ``rows``; ``bound`` gets censor / exposure."""
    zero = np.float32(0.0)
    width, rx = exposure.size, kx.size // 2
    for c in range(width):
        bound[c] = censor / exposure[c]
        count[c] = zero
        total[c] = zero
    n = width - 2 * rx
    inner_bound, inner_count, inner_total = bound[rx:rx + n], count[rx:rx + n], total[rx:rx + n]
    for dy in range(ky.size):
        gy, wr, xr = ky[dy], w[rows[dy]], x[rows[dy]]
        if kx.size == 3:
            _censored_taps3(wr, xr, inner_bound, gy * kx[0], gy * kx[1], gy * kx[2], inner_count, inner_total)
            continue
        for dx in range(kx.size):
            _censored_tap(wr[dx:dx + n], xr[dx:dx + n], inner_bound, gy * kx[dx], inner_count, inner_total)


@kernel
def _censored_taps3(w, x, bound, g0, g1, g2, count, total):
    """Three taps of :func:`_censored_row` in a row, w and x one row of the window (2 longer than ``bound``): one
    loop, which LLVM vectorises, adding them in :func:`_censored_tap`'s order."""
    zero = np.float32(0.0)
    reach2 = np.float32(CONSISTENT_SIGMA * CONSISTENT_SIGMA)
    for c in range(bound.size):
        b, n, t = bound[c], count[c], total[c]
        w0, x0, w1, x1, w2, x2 = w[c], x[c], w[c + 1], x[c + 1], w[c + 2], x[c + 2]
        gap = b - x0
        keep = (w0 > zero) & ((gap <= zero) | (w0 * gap * gap <= reach2))
        n += g0 if keep else zero
        t += g0 * x0 if keep else zero
        gap = b - x1
        keep = (w1 > zero) & ((gap <= zero) | (w1 * gap * gap <= reach2))
        n += g1 if keep else zero
        t += g1 * x1 if keep else zero
        gap = b - x2
        keep = (w2 > zero) & ((gap <= zero) | (w2 * gap * gap <= reach2))
        count[c] = n + (g2 if keep else zero)
        total[c] = t + (g2 * x2 if keep else zero)


@kernel
def _censored_tap(w, x, bound, g, count, total):
    """One tap of :func:`_censored_row`, over aligned 1-D arrays (a loop of its own, which LLVM vectorises)."""
    zero = np.float32(0.0)
    reach2 = np.float32(CONSISTENT_SIGMA * CONSISTENT_SIGMA)
    for c in range(bound.size):
        gap = bound[c] - x[c]
        keep = (w[c] > zero) & ((gap <= zero) | (w[c] * gap * gap <= reach2))
        count[c] += g if keep else zero
        total[c] += g * x[c] if keep else zero


@kernel
def _censored_separable(censored, exposure, w, x, image, bound_only, ky, kx, values, bounds, first, last):
    """The per-level window sums of :func:`censored_pixels` (consistent readings, :func:`_consistent_row`, and
    their sum) at each censored pixel of (H, W) arrays, with OpenCV's arithmetic: a 3-tap row filter (centre tap
    + the pair around it), then a 3- or 5-tap column filter (centre, then the pairs outwards), borders
    reflect-101, each censored pixel's neighbours tested against its own level's bound (``bounds``, of the
    levels ``values``), in rows [first, last). Bit for bit the sums ``smooth`` gives there, at a cost that follows
    the censored pixels, not the number of levels: a row with few of them visits each one's window (its readings'
    reaches made there), a row with many (more than one in DENSE_ROW) sums every pixel's window at once, a loop
    over the row per window row (vectorised), from the reaches of the window's rows made whole once."""
    h, width = censored.shape
    zero, tiny = np.float32(0.0), np.float32(TINY)
    reach = np.empty((h, width), np.float32)
    reached = np.zeros(h, np.bool_)
    rows = np.empty(ky.size, np.int64)
    bound = np.empty(width, np.float32)
    level_count, level_sum = np.empty((ky.size, width), np.float32), np.empty((ky.size, width), np.float32)
    count, total = np.empty(width, np.float32), np.empty(width, np.float32)
    leveled = np.empty(width, np.bool_)
    index = np.empty(width, np.int64)
    window_rows = np.arange(ky.size)
    for r in range(first, last):
        n = count_true(censored[r])
        if n == 0:
            continue
        reflected_rows(r, h, rows)
        if n * DENSE_ROW > width:
            _level_bounds(exposure[r], values, bounds, bound)
            for dy in range(ky.size):
                rr = rows[dy]
                if not reached[rr]:
                    _reach_row(w[rr], x[rr], reach[rr])
                    reached[rr] = True
            for dy in range(ky.size):
                _consistent_row_sums(reach[rows[dy]], x[rows[dy]], bound, kx[0], kx[1], level_count[dy],
                                     level_sum[dy])
            column_sums(level_count, window_rows, ky, count)
            column_sums(level_sum, window_rows, ky, total)
            for c in range(width):
                leveled[c] = censored[r, c] & (bound[c] < np.inf)
            _censored_fill(leveled, x[r], count, total, image[r], bound_only[r])
            continue
        n = true_positions(censored[r], n, index)
        for j in range(n):
            c = index[j]
            pixel_bound = _level_bound(exposure[r, c], values, bounds)
            if pixel_bound == np.inf:
                continue
            for dy in range(ky.size):
                level_count[dy, 0], level_sum[dy, 0] = _consistent_pixel_sums(w[rows[dy]], x[rows[dy]], c,
                                                                              pixel_bound, kx[0], kx[1])
            count_c, total_c = _column_sum_pixel(level_count[:, 0], ky), _column_sum_pixel(level_sum[:, 0], ky)
            image[r, c] = max(total_c / max(count_c, tiny), x[r, c])
            if count_c <= zero:
                bound_only[r, c] = True


@kernel
def _level_bounds(exposure, values, bounds, bound):
    """bound = bounds[j] where exposure == values[j], inf (no level: left alone) elsewhere; one row, vectorised."""
    for c in range(exposure.size):
        bound[c] = np.inf
    for j in range(values.size):
        value, level_bound = values[j], bounds[j]
        for c in range(exposure.size):
            bound[c] = level_bound if exposure[c] == value else bound[c]


@kernel
def _level_bound(exposure, values, bounds):
    """:func:`_level_bounds` of one pixel of exposure ``exposure``."""
    bound = np.float32(np.inf)
    for j in range(values.size):
        bound = bounds[j] if exposure == values[j] else bound
    return bound


@kernel
def _consistent_pixel_sums(w, x, c, bound, k0, k1):
    """:func:`_consistent_row_sums` at pixel ``c`` of one row alone, from the row's w and x (its three readings'
    reaches made here, :func:`_reach`, as :func:`_reach_row` makes a row's)."""
    n = w.size
    zero, one = np.float32(0.0), np.float32(1.0)
    left, right = reflect_101(c - 1, n), reflect_101(c + 1, n)
    a = zero if _reach(w[left], x[left]) < bound else one
    m = zero if _reach(w[c], x[c]) < bound else one
    d = zero if _reach(w[right], x[right]) < bound else one
    return k1 * m + k0 * (a + d), k1 * (m * x[c]) + k0 * (a * x[left] + d * x[right])


@kernel
def _column_sum_pixel(values, ky):
    """:func:`column_sums` of one column (``values``: ky.size)."""
    if ky.size == 3:
        return ky[1] * values[1] + ky[0] * (values[0] + values[2])
    return ky[2] * values[2] + ky[1] * (values[1] + values[3]) + ky[0] * (values[0] + values[4])


@kernel
def _reach_row(w, x, reach):
    """:func:`_reach` of a row's readings."""
    for k in range(w.size):
        reach[k] = _reach(w[k], x[k])


@kernel(inline="always")
def _reach(w, x):
    """x + CONSISTENT_SIGMA sqrt(1 / w) of an uncensored reading (w > 0), -inf else, as :func:`_consistent_row`;
    float32. Inlined into the loops that call it (a call left in place keeps LLVM from vectorising them)."""
    one, tiny, sigma = np.float32(1.0), np.float32(TINY), np.float32(CONSISTENT_SIGMA)
    return np.sqrt(one / max(w, tiny)) * sigma + x if w > 0 else np.float32(-np.inf)


@kernel
def _consistent_sums_at(reach, x, bound, k0, k1, c, count, total):
    """:func:`_consistent_row_sums` at pixel ``c`` alone, its neighbours reflect-101."""
    n = reach.size
    zero, one = np.float32(0.0), np.float32(1.0)
    left, right = reflect_101(c - 1, n), reflect_101(c + 1, n)
    a = zero if reach[left] < bound[c] else one
    b = zero if reach[c] < bound[c] else one
    d = zero if reach[right] < bound[c] else one
    count[c] = k1 * b + k0 * (a + d)
    total[c] = k1 * (b * x[c]) + k0 * (a * x[left] + d * x[right])


@kernel
def _consistent_row_sums(reach, x, bound, k0, k1, count, total):
    """The row filter (k0, k1, k0) of the consistent indicator (reach >= bound[c]) and of it times x, each pixel c
    of the row tested against ``bound[c]``; OpenCV's arithmetic, borders reflect-101."""
    n = reach.size
    zero, one = np.float32(0.0), np.float32(1.0)
    for i in range(n if n < 3 else 2):  # a short row whole, else its two ends, whose windows reflect
        _consistent_sums_at(reach, x, bound, k0, k1, i if n < 3 else i * (n - 1), count, total)
    if n < 3:
        return
    r0, r1, r2, x0, x1, x2 = reach[:n - 2], reach[1:n - 1], reach[2:], x[:n - 2], x[1:n - 1], x[2:]
    b1, c1, t1 = bound[1:n - 1], count[1:n - 1], total[1:n - 1]
    for i in range(n - 2):
        b = b1[i]
        a = zero if r0[i] < b else one
        m = zero if r1[i] < b else one
        d = zero if r2[i] < b else one
        c1[i] = k1 * m + k0 * (a + d)
        t1[i] = k1 * (m * x1[i]) + k0 * (a * x0[i] + d * x2[i])


@kernel
def _level_boxes(censored, key, values, width, boxes):
    """Per level j, a box (first row, last row, first column, last column) holding its censored pixels.

    ``values``: the levels' keys, ascending (at most 63); a pixel's level is
    the number of keys below its own. The box of a level without censored
    pixels has last row -1.
    """
    rows = censored.size // width
    row_bits, col_bits = np.zeros(rows, np.int64), np.zeros(width, np.int64)
    slot = np.empty(width, np.int64)
    for r in range(rows):
        row = slice(r * width, (r + 1) * width)
        if censored[row].any():
            row_bits[r] = _row_level_bits(censored[row], key[row], values, slot, col_bits)
    for j in range(values.size):
        bit = np.int64(1) << j
        boxes[j, 0], boxes[j, 1] = _first_last(row_bits, bit)
        boxes[j, 2], boxes[j, 3] = _first_last(col_bits, bit)


@kernel
def _row_level_bits(censored, key, values, slot, col_bits):
    """Bit j set where a censored pixel of level j lies: in the row (returned), per column (OR-ed into col_bits)."""
    slot[:] = 0
    for j in range(values.size):
        for k in range(key.size):
            slot[k] += key[k] > values[j]
    bits = np.int64(0)
    for k in range(key.size):
        b = np.int64(censored[k]) << slot[k]
        bits |= b
        col_bits[k] |= b
    return bits


@kernel
def _first_last(bits, bit):
    """First and last index of ``bits`` with ``bit`` set; (size, -1) when none."""
    first, last = bits.size, -1
    for i in range(bits.size):
        if bits[i] & bit:
            first = min(first, i)
            last = i
    return first, last


@kernel
def _consistent(w, x, consistent, consistent_x, width, r0, c0, cols, bound):
    """Over a box of ``cols`` columns at (r0, c0): 1 for readings consistent with ``bound``, else 0; and that times x.

    Consistent: an uncensored reading (w > 0) whose reach x + 2 sqrt(v_p) is at least the bound.
    """
    for i in range(consistent.size // cols):
        start, out = (r0 + i) * width + c0, i * cols
        _consistent_row(w[start:start + cols], x[start:start + cols], consistent[out:out + cols],
                        consistent_x[out:out + cols], bound)


@kernel
def _consistent_row(w, x, consistent, consistent_x, bound):
    """One row of :func:`_consistent` (a loop of its own, which LLVM vectorises)."""
    zero, one, tiny, sigma = np.float32(0.0), np.float32(1.0), np.float32(TINY), np.float32(CONSISTENT_SIGMA)
    none = np.float32(-np.inf)  # no reading: consistent with no bound
    for k in range(w.size):
        reach = np.sqrt(one / max(w[k], tiny)) * sigma + x[k] if w[k] > 0 else none
        c = zero if reach < bound else one
        consistent[k] = c
        consistent_x[k] = c * x[k]


@kernel
def _fill_censored(censored, key, x, image, bound_only, count, sum_x, width, value, r0, c0, cols,
                   top, bottom, left, right):
    """At this level's censored pixels (key == value) in rows [top, bottom) and cols [left, right):
    image = max(mean of consistent x, x), from the window sums ``count`` and ``sum_x`` of a box of ``cols``
    columns at (r0, c0); flag empty windows.
    """
    n = right - left
    for r in range(top, bottom):
        at, box = r * width + left, (r - r0) * cols + left - c0
        _fill_row(censored[at:at + n], key[at:at + n], x[at:at + n], image[at:at + n], bound_only[at:at + n],
                  count[box:box + n], sum_x[box:box + n], value)


@kernel
def _fill_row(censored, key, x, image, bound_only, count, sum_x, value):
    """One row of :func:`_fill_censored` (a loop of its own, which LLVM vectorises)."""
    tiny = np.float32(TINY)
    for k in range(x.size):
        if censored[k] and key[k] == value:
            image[k] = max(sum_x[k] / max(count[k], tiny), x[k])
            if count[k] <= 0:
                bound_only[k] = True
