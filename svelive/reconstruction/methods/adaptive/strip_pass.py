"""Steps 1-4 of ``adaptive`` but the censored pixels' own values, as one compiled pass down a strip's rows
(:func:`fused_pass`): the window sums as row filters into rings of rows and column filters of the rings, and the
per-pixel stages between them (weights, residuals, blend)."""

from __future__ import annotations

from functools import lru_cache
from typing import NamedTuple

import numpy as np

from svelive.core.pattern import Pattern
from svelive.jit import kernel
from svelive.reconstruction.methods.adaptive.parameters import BIG, TINY, kernels
from svelive.reconstruction.methods.adaptive.posterior import FEW_NEAR_ZERO, NEAR_MARGIN, POSTERIOR_HIGH, nonnegative
from svelive.reconstruction.methods.base import copy_row, count_true, reflect_101, rows_min, smooth, window_level_row


class PassReadings(NamedTuple):
    """What :func:`fused_pass` reads of a strip.

    Attributes:
        signal, exposure: float32 (H, W), the readings s and their exposures e.
        censored: bool (H, W), the censored readings.
        flagged: bool, the strip holds censored pixels: the chain takes :func:`_weights_censored`.
        every_row: bool, w, wn and x on every row of the strip (the censored step's per-level sums read them
            all, censoring.censored_way), else on the rows the stages after step 1 read.
        exposure_sum: float32 (H, W), the window sums of ``exposure`` (the pattern's, cached), or of
            no rows: computed (of the uncensored exposures) in the pass. Where ``flagged``, read only at rows whose
            window holds no censored reading (the others' are computed), and given only where they are the pass's
            own sums bit for bit (SHARED_SUMS).
    """

    signal: np.ndarray
    exposure: np.ndarray
    censored: np.ndarray
    flagged: bool
    every_row: bool
    exposure_sum: np.ndarray


class PassNoise(NamedTuple):
    """The noise model of :func:`fused_pass` (adaptive's ``noise_model``): float32 1 / gain and floor variance."""

    gain_inv: np.float32
    floor: np.float32


class PassSettings(NamedTuple):
    """The kernels and thresholds of :func:`fused_pass`.

    Attributes:
        ky, kx: float32, the window's binomial kernels (parameters.kernels).
        centre: float32, their centre taps' product; kernel_square: float32, sum G^2 of the window.
        threshold: float32, :func:`_blend`'s, 2 CONTRAST_SIGMA^2 kernel_square.
        coefficients: float32, step 4's polynomial (posterior.posterior_polynomial).
        bottom: float32, the reading s of a raw 0 (minus the black level): step 4's 0 at the bottom of the raw range.
        z2: float32, CONTRAST_SIGMA^2, the wide fallback's candidates' threshold (:func:`_candidates`).
    """

    ky: np.ndarray
    kx: np.ndarray
    centre: np.float32
    kernel_square: np.float32
    threshold: np.float32
    coefficients: np.ndarray
    bottom: np.float32
    z2: np.float32


class PassOutputs(NamedTuple):
    """What :func:`fused_pass` writes: float32 (H, W) but where said.

    Attributes:
        w: the weights; wn: the neighbours' weights (``w`` itself unless ``flagged``).
        x: s / e, (H, W) where ``flagged`` (the censored step reads it; then x, w and wn are set on every
            row if ``every_row``, else where w is), else a ring of the window's height.
        image, estimate, total: in rows [first, last) the result, L^ and its information.
        lower: bool, exposure sum <= 0 where w is set, False elsewhere.
        candidates: bool, the wide fallback's, in rows [first, last).
        variance: 1 / total in rows [first, last), or of no rows: not computed.
    """

    w: np.ndarray
    wn: np.ndarray
    x: np.ndarray
    image: np.ndarray
    estimate: np.ndarray
    total: np.ndarray
    lower: np.ndarray
    candidates: np.ndarray
    variance: np.ndarray


class PassWindow(NamedTuple):
    """The motion tests' window mean :func:`fused_pass` makes beside the method (base.window_level_row).

    Attributes:
        means: float32 (2, H, W), the window mean and its variance in rows [first, last), or of no rows:
            not computed; 0 and an infinite variance where the window holds no uncensored reading.
        noise: float32 (2,), (1 / g, sigma^2) of the sensor.
    """

    means: np.ndarray
    noise: np.ndarray


@kernel
def fused_pass(readings, first, last, noise, settings, outputs, motion_window):
    """Steps 1-4 but the censored pixels' own values, on the rows [first, last) of (H, W) arrays, in one pass
    down the rows: the chain of :func:`_weights` (:func:`_weights_censored` where ``flagged``: the strip holds
    censored pixels), :func:`_residuals`, :func:`_blend`, :func:`_zero_bottom_row` and
    :func:`_candidates` with their window sums between them, each stage a window's half height behind the one
    it reads, and only on the rows the next one reads.

    Each window sum is a row filter into a ring of the window's height of filtered rows, then a column filter
    of the ring's rows (:func:`_row_filter`, :func:`_column_filter`: ``smooth``'s arithmetic and borders,
    reflect-101 at the array's ends), so a stage reads rows the one before has just written, in cache,
    instead of whole arrays; the stage that reads a column filter's sums makes them pixel by pixel in its own
    loop (:func:`_column`), so they are never written to a row and read back. ``readings``: :class:`PassReadings`;
    ``noise``: :class:`PassNoise`; ``settings``: :class:`PassSettings`; ``outputs``: :class:`PassOutputs`. Returns
    (the candidates' count, whether any pixel is ``lower``): the caller fills the lower bounds.

    ``motion_window`` (:class:`PassWindow`): also the motion tests' window mean and its variance (the window
    sums of the uncensored readings are the pilot's, and those of G^2 e and G^2 two more row and column
    filters)."""
    s, e, censored, flagged, every_row, exposure_sum = readings
    gain_inv, floor = noise
    ky, kx, centre, kernel_square, threshold, coefficients, bottom, z2 = settings
    w, wn, x, image, estimate, total, lower, candidates, variance = outputs
    window, window_noise = motion_window
    h, width = s.shape
    ry = ky.size // 2
    windowed = window.shape[1] > 0
    ky2, kx2 = ky * ky, kx * kx
    given = exposure_sum.size > 0
    depth = min(h, 2 * ry + 1)  # a window's rows, reflected at the ends, lie among the last `depth` computed
    square_rows = np.empty((2, depth if windowed else 0, width), np.float32)  # row sums of G^2 e and of G^2
    square_sums = np.empty((2, width if windowed else 0), np.float32)
    signal_rows, exposure_rows = np.empty((depth, width), np.float32), np.empty((depth, width), np.float32)
    lowest_rows = np.empty((depth if flagged else 0, width), np.float32)
    held_rows = np.zeros(h if flagged else 0, np.int64)  # the censored readings of each row
    for r in range(h if flagged else 0):
        held_rows[r] = count_true(censored[r])
    weight_rows, weighted_rows = np.empty((depth, width), np.float32), np.empty((depth, width), np.float32)
    excess_rows, q_rows = np.empty((depth, width), np.float32), np.empty((depth, width), np.float32)
    # m and v_r = v_p + v_m from step 2 until step 3 reads them, ry rows later
    neighbours, residual_variances = np.empty((ry + 1, width), np.float32), np.empty((ry + 1, width), np.float32)
    sums, exposure_scratch, lowest, a, b = (np.empty(width, np.float32), np.empty(width, np.float32),
                                        np.empty(width, np.float32), np.empty(width, np.float32),
                                        np.empty(width, np.float32))
    low, everywhere = np.empty(width, np.bool_), np.empty(width, np.bool_)
    flags, raised = np.empty(width, np.bool_), np.empty(width, np.bool_)  # _blend's scratch
    at_bottom = np.zeros(h, np.int64)
    if windowed and not flagged:  # every reading kept: each row's sums of G^2 are the same, made once
        b[:] = np.float32(1.0)
        for slot in range(depth):
            _row_filter(b, kx2, square_rows[1, slot])
    rows = np.empty(ky.size, np.int64)
    # rows each stage computes: those the next one's windows read (with the censored step's per-level sums, step 1
    # everywhere; its other ways read w and x a window's half height around the rows [first, last))
    first1, last1 = (0, h) if every_row else (max(first - 2 * ry, 0), min(last + 2 * ry, h))
    first0, last0 = max(first1 - ry, 0), min(last1 + ry, h)
    first2, last2 = max(first - ry, 0), min(last + ry, h)
    lower[:first1] = False
    lower[last1:] = False
    count, lowered = 0, False
    for i in range(h + 3 * ry):
        r = i
        if first0 <= r < last0:  # row filters of the readings and exposures (uncensored ones)
            if flagged:
                held = held_rows[r]  # the row's censored readings: without any, the row as it is
                # the kept exposures' sums and the least exposures are read only by windows holding a censored
                # reading (step 1; elsewhere the pattern's sums where given): those of the rows 2 ry around
                near = _held_near(held_rows, r, 2 * ry)
                _row_filter(_uncensored(s[r], censored[r], held, a), kx, signal_rows[r % depth])
                kept = _uncensored(e[r], censored[r], held, a)
                if near or not given:
                    _row_filter(kept, kx, exposure_rows[r % depth])
                if windowed:
                    _row_filter(kept, kx2, square_rows[0, r % depth])
                    _kept(censored[r], b)
                    _row_filter(b, kx2, square_rows[1, r % depth])
                if held > 0:
                    _row_least(e[r], censored[r], kx.size // 2, a, lowest_rows[r % depth])
                elif near:
                    lowest_rows[r % depth] = np.float32(BIG)
            else:
                _row_filter(s[r], kx, signal_rows[r % depth])
                if not given:
                    _row_filter(e[r], kx, exposure_rows[r % depth])
                if windowed:  # (the row sums of G^2 over the kept readings are the constant ones below)
                    _row_filter(e[r], kx2, square_rows[0, r % depth])
            at_bottom[r] = _count_at_most(s[r], bottom)
        r = i - ry
        if first1 <= r < last1:  # step 1: w (wn), and the row filters of wn and wn x
            _window_rows(r, h, depth, rows)
            in_window = windowed and first <= r < last
            if in_window:  # the motion tests' window mean, below, reads the sums too
                _column_filter(signal_rows, rows, ky, sums)
                signal_column = _summed(sums)
            else:
                signal_column = _column(signal_rows, rows, ky, sums)
            held_in = flagged and _held_near(held_rows, r, ry)  # a censored reading in the window's rows
            if given and not held_in:  # every exposure of the window kept: the pattern's sums
                exposure_row = exposure_sum[r]
            else:
                _column_filter(exposure_rows, rows, ky, exposure_scratch)
                exposure_row = exposure_scratch
            if flagged:
                if held_in:
                    rows_min(lowest_rows, rows, lowest)
                else:  # no censored reading in the window's rows
                    lowest[:] = np.float32(BIG)
                _weights_censored(signal_column, exposure_row, s[r], e[r], censored[r], lowest, w[r], x[r], wn[r], a,
                                  gain_inv, floor, centre)
            else:
                _weights(signal_column, exposure_row, s[r], e[r], w[r], x[r % x.shape[0]], a, gain_inv, floor,
                         centre)
            lowered |= _at_most_zero(exposure_row, lower[r])
            if in_window:  # the motion tests' window mean, from the same sums
                _column_filter(square_rows[0], rows, ky2, square_sums[0])
                _column_filter(square_rows[1], rows, ky2, square_sums[1])
                window_level_row(sums, exposure_row, square_sums[0], square_sums[1], window_noise[0],
                                 window_noise[1], window[0, r], window[1, r])
            _row_filter(wn[r], kx, weight_rows[r % depth])
            _row_filter(a, kx, weighted_rows[r % depth])
        r = i - 2 * ry
        if first2 <= r < last2:  # step 2: m and v_m (into `estimate` until step 3), the row filters of b^2's terms
            _window_rows(r, h, depth, rows)
            _residuals(_column(weight_rows, rows, ky, sums), _column(weighted_rows, rows, ky, exposure_scratch),
                       estimate[r], neighbours[r % (ry + 1)], wn[r], w[r], x[r % x.shape[0]], a, b,
                       residual_variances[r % (ry + 1)], centre, kernel_square)
            _row_filter(a, kx, excess_rows[r % depth])
            _row_filter(b, kx, q_rows[r % depth])
        r = i - 3 * ry
        if first <= r < last:  # steps 3 and 4, 0 at the bottom of the raw range, the wide fallback's candidates
            _window_rows(r, h, depth, rows)
            _blend(_column(excess_rows, rows, ky, sums), _column(q_rows, rows, ky, exposure_scratch), image[r],
                   total[r], estimate[r], neighbours[r % (ry + 1)], residual_variances[r % (ry + 1)], w[r],
                   x[r % x.shape[0]], e[r], gain_inv, floor, threshold, coefficients, flags, raised)
            _zero_bottom_row(s, at_bottom, r, bottom, ry, kx.size // 2, low, everywhere, image[r])
            if variance.size > 0:
                _reciprocal(total[r], variance[r])
            count += _candidates(estimate[r], total[r], image[r], censored[r], lower[r], candidates[r], z2)
    return count, lowered


@kernel
def _uncensored(values, censored, held, out):
    """``values`` with 0 where ``censored``: ``values`` itself where none of them is (``held``: their count), else
    made into ``out``."""
    if held == 0:
        return values
    for c in range(out.size):
        out[c] = np.float32(0.0) if censored[c] else values[c]
    return out


@kernel
def _held_near(held_rows, r, reach):
    """Whether a row within ``reach`` of row ``r`` holds a censored reading (``held_rows``: each row's count); the
    rows a window of that half height reads at the array's ends (reflect-101) lie among them."""
    for row in range(max(r - reach, 0), min(r + reach + 1, held_rows.size)):
        if held_rows[row] > 0:
            return True
    return False


@kernel
def _kept(censored, out):
    """out = 1 where uncensored, 0 where censored."""
    for c in range(out.size):
        out[c] = np.float32(0.0) if censored[c] else np.float32(1.0)


@kernel
def _row_least(e, censored, rx, scratch, out):
    """out = the least exposure of the censored readings within ``rx`` of each pixel of a row (BIG where none),
    borders reflect-101; the middle as vectorised loops (``scratch``: a row)."""
    n, big = e.size, np.float32(BIG)
    for c in range(n):
        scratch[c] = e[c] if censored[c] else big
    ends = min(rx, n)  # the row's ends, whose windows reflect: [0, ends) and [max(n - rx, ends), n)
    for i in range(ends + n - max(n - rx, ends)):
        c = i if i < ends else max(n - rx, ends) + i - ends
        least = big
        for dx in range(-rx, rx + 1):
            least = min(least, scratch[reflect_101(c + dx, n)])
        out[c] = least
    inner = n - 2 * rx
    if inner <= 0:
        return
    middle, first = out[rx:rx + inner], scratch[:inner]
    if rx == 0:
        copy_row(first, middle)
        return
    second = scratch[1:1 + inner]
    for i in range(inner):
        middle[i] = min(first[i], second[i])
    for dx in range(2, 2 * rx + 1):
        shifted = scratch[dx:dx + inner]
        for i in range(inner):
            middle[i] = min(middle[i], shifted[i])


@kernel
def _window_rows(r, h, depth, rows):
    """rows = the ring slots (row modulo ``depth``) of the window's rows around row ``r`` of ``h``, reflect-101."""
    ry = rows.size // 2
    for dy in range(rows.size):
        rows[dy] = reflect_101(r + dy - ry, h) % depth


@kernel
def _row_filter(source, k, out):
    """out = the symmetric filter ``k`` (odd taps) along one row, borders reflect-101, with ``smooth``'s
    arithmetic: the centre tap, then the pairs of mirrored taps outwards; the middle as vectorised loops."""
    n, rk = source.size, k.size // 2
    ends = min(rk, n)  # the row's ends, whose windows reflect: [0, ends) and [max(n - rk, ends), n)
    for i in range(ends + n - max(n - rk, ends)):
        c = i if i < ends else max(n - rk, ends) + i - ends
        acc = k[rk] * source[c]
        for d in range(1, rk + 1):
            acc += k[rk - d] * (source[reflect_101(c - d, n)] + source[reflect_101(c + d, n)])
        out[c] = acc
    inner = n - 2 * rk
    if inner <= 0:
        return
    middle = out[rk:rk + inner]
    if rk == 1:
        k0, k1 = k[0], k[1]
        left, centre, right = source[:inner], source[1:1 + inner], source[2:2 + inner]
        for i in range(inner):
            middle[i] = k1 * centre[i] + k0 * (left[i] + right[i])
        return
    centre, kc = source[rk:rk + inner], k[rk]
    for i in range(inner):
        middle[i] = kc * centre[i]
    for d in range(1, rk + 1):
        left, right, kd = source[rk - d:rk - d + inner], source[rk + d:rk + d + inner], k[rk - d]
        for i in range(inner):
            middle[i] += kd * (left[i] + right[i])


@kernel
def _column_filter(values, rows, k, out):
    """out = the symmetric filter ``k`` down ``values``' rows ``rows`` (the window's, top to bottom) with
    ``smooth``'s arithmetic: the centre tap, then the pairs outwards (:func:`column_sums` for 3 or 5 taps)."""
    if k.size == 3 or k.size == 5:
        column_sums(values, rows, k, out)
        return
    rk = k.size // 2
    centre, kc = values[rows[rk]], k[rk]
    for i in range(out.size):
        out[i] = kc * centre[i]
    for d in range(1, rk + 1):
        above, below, kd = values[rows[rk - d]], values[rows[rk + d]], k[rk - d]
        for i in range(out.size):
            out[i] += kd * (above[i] + below[i])


@kernel
def _column(values, rows, k, scratch):
    """The column filter ``k`` down ``values``' rows ``rows`` as :func:`_three` and :func:`_five` read it pixel by
    pixel, in the loop of the stage that reads the sums (no row of sums written and read back): the window's rows as
    views where ``k`` has 3 or 5 taps, else the sums made into ``scratch`` (a row) by :func:`_column_filter`."""
    if k.size == 3:
        return (values[rows[0]], values[rows[1]], values[rows[2]], values[rows[2]], values[rows[2]], k[0], k[1],
                k[1], 3)
    if k.size == 5:
        return (values[rows[0]], values[rows[1]], values[rows[2]], values[rows[3]], values[rows[4]], k[0], k[1],
                k[2], 5)
    _column_filter(values, rows, k, scratch)
    return _summed(scratch)


@kernel
def _summed(sums):
    """Sums made already (a row), as a :func:`_column`: the stages read them as they are."""
    one = np.float32(1.0)
    return sums, sums, sums, sums, sums, one, one, one, 1


@kernel
def _three(column, i):
    """Pixel ``i`` of a :func:`_column` of 3 taps: :func:`column_sums`' arithmetic."""
    a, b, c, _, _, k0, k1, _, _ = column
    return k1 * b[i] + k0 * (a[i] + c[i])


@kernel
def _five(column, i):
    """Pixel ``i`` of a :func:`_column` of 5 taps: :func:`column_sums`' arithmetic."""
    a, b, c, d, f, k0, k1, k2, _ = column
    return k2 * c[i] + k1 * (b[i] + d[i]) + k0 * (a[i] + f[i])


@kernel
def _count_at_most(values, level):
    """How many of ``values`` are <= ``level``."""
    n = 0
    for c in range(values.size):
        n += values[c] <= level
    return n


@kernel
def _at_most_zero(values, out):
    """out = values <= 0; whether any is."""
    for c in range(values.size):
        out[c] = values[c] <= np.float32(0.0)
    return count_true(out) > 0  # counted apart, so that the loop above vectorises


@kernel
def _reciprocal(a, out):
    """out = 1 / a."""
    for c in range(out.size):
        out[c] = np.float32(1.0) / a[c]


@kernel
def _candidates(estimate, information, image, censored, lower, out, z2):
    """out = the pixels whose result cannot tell the level from 0 (L^ <= 0 or L^^2 information < z2), neither
    censored nor a lower bound nor set to 0 at the bottom of the raw range; flat arrays; their count."""
    zero = np.float32(0.0)
    for k in range(out.size):
        e = estimate[k]
        out[k] = ((e <= zero) | (e * e * information[k] < z2)) & (image[k] > zero) & ~censored[k] & ~lower[k]
    return count_true(out)  # counted apart: a count inside the loop above keeps LLVM from vectorising it


@kernel
def _zero_bottom_row(s, at_bottom, r, bottom, ry, rx, low, everywhere, out):
    """out = 0, in place, where every reading of the pixel's window (2 ry + 1 rows, 2 rx + 1 columns, borders
    reflect-101) lies at the bottom of the raw range (raw 0, a signal of ``bottom`` = -black): clipped there,
    such readings say only "at most", as saturated ones say "at least", and their tightest answer is 0 (a black
    frame stays black; :func:`nonnegative` would lift it). Row ``r`` of (H, W) ``s``, ``out`` its row of the
    image; tested only if every row of its window holds a reading at the bottom (``at_bottom``: their counts
    per row): the window's rows, then its columns, as vectorised loops (``low`` and ``everywhere``: scratch
    rows), each one pass for windows of 3 or 5 rows and 3 columns; ``out`` is written only if a pixel is 0."""
    h, width = s.shape
    for dy in range(2 * ry + 1):
        if at_bottom[reflect_101(r + dy - ry, h)] == 0:
            return
    if ry == 1:  # the window's rows in one loop (a dim frame tests most rows, and few pixels are 0)
        _low_three(s[reflect_101(r - 1, h)], s[r], s[reflect_101(r + 1, h)], bottom, low)
    elif ry == 2:
        _low_five(s[reflect_101(r - 2, h)], s[reflect_101(r - 1, h)], s[r], s[reflect_101(r + 1, h)],
                  s[reflect_101(r + 2, h)], bottom, low)
    else:
        low[:] = True
        for dy in range(2 * ry + 1):
            row = s[reflect_101(r + dy - ry, h)]
            for c in range(width):
                low[c] &= row[c] <= bottom
    found = False
    ends = min(rx, width)  # the row's ends, whose windows reflect: [0, ends) and [max(width - rx, ends), width)
    for i in range(ends + width - max(width - rx, ends)):
        c = i if i < ends else max(width - rx, ends) + i - ends
        everywhere[c] = True
        for dx in range(2 * rx + 1):
            everywhere[c] &= low[reflect_101(c + dx - rx, width)]
        found |= everywhere[c]
    inner = width - 2 * rx
    if inner > 0:
        middle = everywhere[rx:rx + inner]
        if rx == 1:
            left, centre, right = low[:inner], low[1:1 + inner], low[2:2 + inner]
            for i in range(inner):
                both = left[i] & centre[i] & right[i]
                middle[i] = both
                found |= both
        else:
            middle[:] = True
            for dx in range(2 * rx + 1):
                shifted = low[dx:dx + inner]
                for i in range(inner):
                    middle[i] &= shifted[i]
            found |= count_true(middle) > 0
    if not found:
        return
    for c in range(width):
        out[c] = np.float32(0.0) if everywhere[c] else out[c]


@kernel
def _low_three(a, b, c, bottom, low):
    """low = a, b and c (rows) all <= ``bottom``."""
    for i in range(low.size):
        low[i] = (a[i] <= bottom) & (b[i] <= bottom) & (c[i] <= bottom)


@kernel
def _low_five(a, b, c, d, f, bottom, low):
    """low = a, b, c, d and f (rows) all <= ``bottom``."""
    for i in range(low.size):
        low[i] = (a[i] <= bottom) & (b[i] <= bottom) & (c[i] <= bottom) & (d[i] <= bottom) & (f[i] <= bottom)


#: The windows (rows, columns) whose OpenCV sums (base.smooth, which makes :func:`pattern_exposure_sum`) the pass's
#: own row and column filters repeat bit for bit on any float32 values (tests/test_adaptive_kernels.py), so that a
#: strip holding censored readings may read the pattern's sums where its window holds none (a 7-row column or a
#: 5-column row filter of OpenCV's rounds otherwise).
SHARED_SUMS = ((3, 3), (5, 3))


@lru_cache(maxsize=16)
def pattern_exposure_sum(pattern: Pattern, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Window sum of the exposure map and the map's first tile; float32; read-only.

    Strips start on whole tiles, so every strip of one height shares them
    (the first tile tells a caller whether its exposures have that phase).
    """
    ky, kx = kernels(pattern.shape)
    exposure = pattern.exposure_map(shape)
    exposure_sum = smooth(exposure, ky, kx)
    first_tile = exposure[:pattern.shape[0], :pattern.shape[1]].copy()
    for array in (exposure_sum, first_tile):
        array.setflags(write=False)
    return exposure_sum, first_tile


@kernel
def _inverse_variance(signal_sum, exposure_sum, s_valid, e, e_valid, gain_inv, floor, centre):
    """w = e e_valid / (e L0 / g + sigma^2) at the pilot L0 = max(sum s / sum e, 0) of the window *without the pixel*
    (its own reading would make its weight fall as it reads high: a bias low); 0 where e_valid = 0."""
    rest = max(exposure_sum - centre * e_valid, np.float32(TINY))
    pilot = max((signal_sum - centre * s_valid) / rest, np.float32(0.0))
    return e * e_valid / (pilot * e * gain_inv + floor)


@kernel
def _weights(signal_sum, exposure_sum, s, e, w, x, wx, gain_inv, floor, centre):
    """Frame without censored pixels: w of every reading, x = s / e, and w x. ``signal_sum``: a :func:`_column`."""
    arrays, n, taps = (exposure_sum, s, e, w, x, wx, gain_inv, floor, centre), w.size, signal_sum[8]
    for k in range(n if taps == 3 else 0):  # a loop for each way of summing (_column), which LLVM vectorises
        _weight(k, _three(signal_sum, k), arrays)
    for k in range(n if taps == 5 else 0):
        _weight(k, _five(signal_sum, k), arrays)
    for k in range(n if taps == 1 else 0):
        _weight(k, signal_sum[0][k], arrays)


@kernel
def _weight(k, signal_sum, arrays):
    """Pixel k of :func:`_weights`."""
    exposure_sum, s, e, w, x, wx, gain_inv, floor, centre = arrays
    wk = _inverse_variance(signal_sum, exposure_sum[k], s[k], e[k], e[k], gain_inv, floor, centre)
    xk = s[k] / e[k]
    w[k] = wk
    x[k] = xk
    wx[k] = wk * xk


@kernel
def _weights_censored(signal_sum, exposure_sum, s, e, censored, lowest, w, x, wn, wx, gain_inv, floor, centre):
    """w (0 at censored pixels), x = s / e; wn = w but 0 next to a censored pixel of lower or equal exposure; wn x.
    ``signal_sum``: a :func:`_column`."""
    arrays = (exposure_sum, s, e, censored, lowest, w, x, wn, wx, gain_inv, floor, centre)
    n, taps = w.size, signal_sum[8]
    for k in range(n if taps == 3 else 0):  # a loop for each way of summing (_column), which LLVM vectorises
        _weight_censored(k, _three(signal_sum, k), arrays)
    for k in range(n if taps == 5 else 0):
        _weight_censored(k, _five(signal_sum, k), arrays)
    for k in range(n if taps == 1 else 0):
        _weight_censored(k, signal_sum[0][k], arrays)


@kernel
def _weight_censored(k, signal_sum, arrays):
    """Pixel k of :func:`_weights_censored`."""
    exposure_sum, s, e, censored, lowest, w, x, wn, wx, gain_inv, floor, centre = arrays
    zero = np.float32(0.0)
    c = censored[k]
    wk = _inverse_variance(signal_sum, exposure_sum[k], zero if c else s[k], e[k], zero if c else e[k], gain_inv, floor,
                           centre)
    xk = s[k] / e[k]
    w[k] = wk
    x[k] = xk
    wnk = zero if lowest[k] <= e[k] else wk
    wn[k] = wnk
    wx[k] = wnk * xk


@kernel
def _residuals(weight_sum, weighted_sum, var_m, m, wn, w, x, excess_q, q, var_r, centre, kernel_square):
    """Neighbour estimate and the terms of b^2, with v_r = v_p + v_m: q = 1 / v_r^2, excess_q = q ((x - m)^2 - v_r);
    ``var_r`` = v_r (:func:`_blend` reads it).

    ``weight_sum`` and ``weighted_sum`` (each a :func:`_column`): the window sums of wn and wn x; ``var_m`` and
    ``m`` are set to v_m and m (the sums without the centre pixel).
    """
    arrays, n, taps = (var_m, m, wn, w, x, excess_q, q, var_r, centre, kernel_square), w.size, weight_sum[8]
    for k in range(n if taps == 3 else 0):  # a loop for each way of summing (_column), which LLVM vectorises
        _residual(k, _three(weight_sum, k), _three(weighted_sum, k), arrays)
    for k in range(n if taps == 5 else 0):
        _residual(k, _five(weight_sum, k), _five(weighted_sum, k), arrays)
    for k in range(n if taps == 1 else 0):
        _residual(k, weight_sum[0][k], weighted_sum[0][k], arrays)


@kernel
def _residual(k, weight_sum, weighted_sum, arrays):
    """Pixel k of :func:`_residuals`."""
    var_m, m, wn, w, x, excess_q, q, var_r, centre, kernel_square = arrays
    one, tiny = np.float32(1.0), np.float32(TINY)
    sum_w = max(weight_sum - centre * wn[k], tiny)  # no neighbours: m = 0 with a huge variance
    mk = (weighted_sum - centre * (wn[k] * x[k])) / sum_w
    var_mk = kernel_square / sum_w
    var_rk = one / max(w[k], tiny) + var_mk  # censored: v_p ~ 1 / tiny, so no evidence
    d = x[k] - mk
    qk = one / (var_rk * var_rk)
    m[k] = mk
    var_m[k] = var_mk
    var_r[k] = var_rk
    excess_q[k] = (d * d - var_rk) * qk
    q[k] = qk


#: Significance, in standard deviations of the pixel's own residual x - m (variance v_p + v_m), of "m is biased
#: at this pixel": the window's squared-bias estimate B weighs its residuals by their precision, so beside a
#: small bright feature the dark side's many precise readings outvote it and the feature's noisier pixels took
#: about half of m (a 3x3 light's edge rows of a 1/1/8/8 frame read half their level). A residual beyond this
#: many deviations is structure whatever the window says; at 5 noise alone passes it at about one pixel in
#: 1.7 million (two-sided), about one a 1920x1200 frame.
OWN_SIGMA = 5.0


@kernel
def _blend(excess_sum, q_sum, image, total, var_m, m, var_r, w, x, e, gain_inv, floor, threshold, coefficients, flags,
           raised):
    """The result: exp(E[log L]) of L ~ N(L^, 1 / total) restricted to L >= 0 (:func:`nonnegative`), with
    L^ = m + (x - m) w / total, total = w + 1 / (b^2 + v_m), b^2 = max(B - threshold SE, 0), and at least
    the pixel's own excess (x - m)^2 - OWN_SIGMA^2 (v_p + v_m) where that is positive.

    Where that own excess is positive (the pixel is not at its neighbours' level), the reading's information in
    ``total`` (not in L^'s weights) is that of the model at the lower of the pilot's level and L^ (``e`` the
    pixel's exposure, ``gain_inv`` and ``floor`` the model's): the pilot is its neighbours' level, and beside
    light it overstates a dark pixel's noise, which step 4 and the wide fallback then read as a level they cannot
    tell from 0 (5 stops dim, dark rings 2 px wide on a saturated disc came out at about 3 of their deviations above
    0: docs/peers.md).

    B = sum excess_q / sum q is the window's estimate of the squared bias, SE its
    standard error under a flat scene, sqrt(2 kernel_square / sum q) (each
    residual's squared excess has variance 2 v_r^2 = 2 / q). ``threshold``:
    CONTRAST_SIGMA^2 * 2 kernel_square, so b^2 = max(B - sqrt(threshold / sum q), 0).
    ``excess_sum`` and ``q_sum`` (each a :func:`_column`): the window sums of excess_q and q; ``image`` and
    ``total`` are set to the result and the information, and ``var_m`` to L^.
    ``var_r``: v_p + v_m, as :func:`_residuals` made it (1 / max(w, TINY) + v_m).
    ``flags`` and ``raised``: bool scratch of the arrays' size N.
    The information at L^ (a division) is computed only in rows holding a pixel that takes it.
    """
    zero = np.float32(0.0)
    high = np.float32(POSTERIOR_HIGH * POSTERIOR_HIGH)
    arrays, n, taps = (image, total, var_m, m, var_r, w, x, raised, threshold), w.size, q_sum[8]
    lifted = False  # only whether any is: a count (int64 lanes) made LLVM take 8 float lanes, not 16
    for k in range(n if taps == 3 else 0):  # a loop for each way of summing (_column), which LLVM vectorises
        lifted |= _blended(k, _three(q_sum, k), _three(excess_sum, k), arrays)
    for k in range(n if taps == 5 else 0):
        lifted |= _blended(k, _five(q_sum, k), _five(excess_sum, k), arrays)
    for k in range(n if taps == 1 else 0):
        lifted |= _blended(k, q_sum[0][k], excess_sum[0][k], arrays)
    dark = 0
    if not lifted:  # the pixels near 0, counted apart
        for k in range(w.size):
            estimate = var_m[k]
            dark += (estimate <= zero) | (estimate * estimate * total[k] < high)
    else:  # a row holding such pixels: their reading's information at L^ (the counts of the new t)
        for k in range(w.size):
            ek, estimate = e[k], var_m[k]
            at_level = ek * ek / (max(estimate, zero) * ek * gain_inv + floor)
            t = total[k] + (max(at_level - w[k], zero) if raised[k] else zero)
            total[k] = t
            dark += (estimate <= zero) | (estimate * estimate * t < high)
    if dark == 0:
        return
    if dark * FEW_NEAR_ZERO >= w.size:
        nonnegative(image, var_m, total, coefficients)
        return
    _nonnegative_runs(image, var_m, total, coefficients, flags)  # few pixels near 0 (a bright scene)


#: :func:`_nonnegative_runs`' columns tested at once: a multiple of 8 (a word of flags).
NEAR_RUN = 64


@kernel
def _nonnegative_runs(image, estimate, information, coefficients, near):
    """:func:`nonnegative` on the runs of NEAR_RUN columns that hold a pixel it may change (L^ <= 0 or within a
    little more than POSTERIOR_HIGH deviations of 0: posterior.NEAR_MARGIN), on flat arrays; it leaves the
    others' values as they are, so the result is that of the whole row's. ``near``: bool scratch of their size.

    Packing those pixels into short arrays (a kernel of posterior until single86) cost as much as the whole row:
    the packing is a scalar loop (each position depends on the count before it), here the test is a vectorised
    one."""
    zero, loose = np.float32(0.0), np.float32(POSTERIOR_HIGH * POSTERIOR_HIGH * NEAR_MARGIN)
    n = image.size
    for k in range(n):
        value = estimate[k]
        near[k] = (value <= zero) | (value * value * information[k] < loose)
    words, per = near[:n // 8 * 8].view(np.uint64), NEAR_RUN // 8
    run = -1  # the first column of the run being gathered, -1 outside one
    for start in range(0, n, NEAR_RUN):
        held = False
        for word in range(start // 8, min(start // 8 + per, words.size)):
            held |= words[word] != 0
        for k in range(max(start, words.size * 8), min(start + NEAR_RUN, n)):  # the columns past the whole words
            held |= near[k]
        if held and run < 0:
            run = start
        elif not held and run >= 0:
            nonnegative(image[run:start], estimate[run:start], information[run:start], coefficients)
            run = -1
    if run >= 0:
        nonnegative(image[run:], estimate[run:], information[run:], coefficients)


@kernel
def _blended(k, q_sum, excess_sum, arrays):
    """Pixel k of :func:`_blend`'s first loop (without branches, which LLVM vectorises): whether it is lifted."""
    image, total, var_m, m, var_r, w, x, raised, threshold = arrays
    zero, one, tiny = np.float32(0.0), np.float32(1.0), np.float32(TINY)
    own_z2 = np.float32(OWN_SIGMA * OWN_SIGMA)
    weight = max(q_sum, tiny)
    d = x[k] - m[k]
    own = d * d - own_z2 * var_r[k]  # the pixel's own evidence of m's bias
    excess = max(max(excess_sum / weight - np.sqrt(threshold / weight), zero), own) + var_m[k]
    t = one / excess + w[k]
    estimate = m[k] + (x[k] - m[k]) * (w[k] / t)
    lift = (own > zero) & (w[k] > zero)
    image[k] = estimate
    var_m[k] = estimate  # kept for the pixels near 0, below
    total[k] = t
    raised[k] = lift
    return lift


@kernel
def column_sums(values, rows, ky, out):
    """The column filter ``ky`` (3 or 5 taps) over ``values``' rows ``rows`` (the window's, top to bottom):
    OpenCV's arithmetic, centre tap first, then the pairs outwards."""
    if ky.size == 3:
        a, b, c = values[rows[0]], values[rows[1]], values[rows[2]]
        k0, k1 = ky[0], ky[1]
        for i in range(out.size):
            out[i] = k1 * b[i] + k0 * (a[i] + c[i])
    else:
        a, b, c, d, e = values[rows[0]], values[rows[1]], values[rows[2]], values[rows[3]], values[rows[4]]
        k0, k1, k2 = ky[0], ky[1], ky[2]
        for i in range(out.size):
            out[i] = k2 * c[i] + k1 * (b[i] + d[i]) + k0 * (a[i] + e[i])
