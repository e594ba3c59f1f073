"""Clipped channels (svelive.reconstruction.colour, "Highlights"): the white balance from the cells
(:func:`white_balance`), and each cell's channel values with the censoring and highlight rules, a clipped
channel raised to the white-balanced level of the measured ones (:func:`_cell_values_row`)."""

from __future__ import annotations

import numpy as np

from svelive.jit import kernel

#: Cells whose every channel is measured to 1 / WHITE_SNR (relative standard deviation) give the white balance.
WHITE_SNR = 10.0
#: Fewer such cells than this: no white balance (neutral is 1, 1, 1).
WHITE_MIN_CELLS = 16
#: About this many cells are looked at for the white balance (every n-th row and column of cells: a
#: median needs no more, and a small frame's every cell counts).
WHITE_CELLS = 4096


def white_balance(numerator: np.ndarray, denominator: np.ndarray, info: np.ndarray, censored: np.ndarray,
                  share: np.ndarray, spread: float) -> np.ndarray:
    """Camera RGB of a neutral surface (G = 1), float32 (3,), from the smoothed cell sums (3, Hc, Wc).

    The median of R / G and B / G of the smoothed cell values over about WHITE_CELLS cells (every
    n-th row and column of them) away from channels with only censored readings (``censored``
    (Hc, Wc), 1 within 3x3 cells of one; other censored readings are allowed, a
    longest exposure may clip over a whole bright ground, and the median outvotes the few cells
    at a highlight's border where the surviving readings are the darker ones) and whose luminance
    sum_c n_c C_c is measured to 1 / WHITE_SNR (its variance sum_c n_c^2 spread / info_c) and
    every channel above 0 (a synthetic frame may hold a channel at 0 over a bright area):
    chosen by the luminance, not by each channel's own noisy value, which would favour cells
    where that channel read high. (1, 1, 1) when fewer than WHITE_MIN_CELLS cells qualify.
    """
    step = slice(None, None, max(int(np.sqrt(numerator[0].size / WHITE_CELLS)), 1))
    num, den, n = numerator[:, step, step], denominator[:, step, step], info[:, step, step]
    with np.errstate(divide="ignore", invalid="ignore"):
        values = num / den
        lum = np.tensordot(share, values, 1)
        variance = np.tensordot(share * share * spread, 1 / n, 1)
        good = ((censored[step, step] == 0) & np.all((den > 0) & (values > 0), axis=0)
                & (lum * lum >= WHITE_SNR ** 2 * variance))
    if np.count_nonzero(good) < WHITE_MIN_CELLS:
        return np.ones(3, np.float32)
    r, g, b = (values[c][good] for c in range(3))
    return np.array([np.median(r / g), 1.0, np.median(b / g)], np.float32)  # finite, > 0: every value is


@kernel
def _cell_values_row(numerator, denominator, mean, info, bound, white, out, i, o):
    """Each cell's C_c of cell row ``i`` into row ``o`` of ``out`` (3, R, Wc), from the smoothed sums ``numerator``
    / ``denominator`` (or, for each cell's own readings alone, ``weighted`` / ``kept``) and the cells'
    statistics (:func:`_cell_stats`), (3, Hc, Wc) each: the censoring and highlight rules (package docstring).
    One loop over the cells of the row (which vectorises), each cell's three channels in registers (as three loops
    over the row, its values and their brightest written into scratch rows and read again between them, the share
    pass took 0.9 ms more a 1920x1200 frame)."""
    zero, one, none = np.float32(0.0), np.float32(1.0), np.float32(-1.0)
    w0, w1, w2 = white[0], white[1], white[2]
    i0, i1, i2 = one / w0, one / w1, one / w2
    r0, r1, r2 = out[0, o], out[1, o], out[2, o]
    for j in range(r0.size):
        v0, m0 = _channel_value(numerator[0, i, j], denominator[0, i, j], mean[0, i, j], info[0, i, j], bound[0, i, j])
        v1, m1 = _channel_value(numerator[1, i, j], denominator[1, i, j], mean[1, i, j], info[1, i, j], bound[1, i, j])
        v2, m2 = _channel_value(numerator[2, i, j], denominator[2, i, j], mean[2, i, j], info[2, i, j], bound[2, i, j])
        # the brightest of the measured channels' C / white (-1: none measured)
        top = max(max(max(none, v0 * i0 if m0 else none), v1 * i1 if m1 else none), v2 * i2 if m2 else none)
        # clipped channels at least the white-balanced level of the measured ones
        v0 = v0 if m0 else max(v0, w0 * top)
        v1 = v1 if m1 else max(v1, w1 * top)
        v2 = v2 if m2 else max(v2, w2 * top)
        # every channel only a bound: neutral white at the largest
        largest = max(v0 / w0, max(v1 / w1, v2 / w2))
        bounded = top < zero
        r0[j] = w0 * largest if bounded else v0
        r1[j] = w1 * largest if bounded else v1
        r2[j] = w2 * largest if bounded else v2


@kernel(inline="always")
def _channel_value(num, den, m, n, b):
    """(C, measured) of one channel of a cell (:func:`_cell_values_row`): the smoothed value, or with censored
    readings (the uncensored neighbours are the darker ones, and those consistent with the bound the brighter) the
    cell's own readings alone (at least their bound); measured: an uncensored reading in the cell, or (a cell at the
    frame's edge without the channel's pixels) none censored and some around."""
    zero = np.float32(0.0)
    smoothed = num / den if den > zero else zero
    return max(max(m, b) if b > zero else smoothed, zero), (n > zero) | ((b <= zero) & (den > zero))
