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
def _cell_values_row(numerator, denominator, mean, info, bound, white, out, brightest, i, o):
    """Each cell's C_c of cell row ``i`` into row ``o`` of ``out`` (3, R, Wc), from the smoothed sums ``numerator``
    / ``denominator`` (or, for each cell's own readings alone, ``weighted`` / ``kept``) and the cells'
    statistics (:func:`_cell_stats`), (3, Hc, Wc) each: the censoring and highlight rules (package docstring).
    ``brightest``: (Wc,) scratch. Loops over the cells of the row (which vectorise)."""
    zero, one, none = np.float32(0.0), np.float32(1.0), np.float32(-1.0)
    # (the loops below spelt out without short-circuits, conditional stores or re-reads of what they wrote, and
    # each plane's row as a row of its own: so written they vectorise with plain loads and stores; as a choice of
    # ``or`` and stores into out[c, o, j] they took masked scatters, 2.1 times the time)
    # brightest: max over the measured channels of C / white (-1: none measured)
    brightest[:] = none
    for c in range(3):
        num, den, m, n, b, row = numerator[c, i], denominator[c, i], mean[c, i], info[c, i], bound[c, i], out[c, o]
        inverse = one / white[c]
        for j in range(row.size):
            smoothed = num[j] / den[j] if den[j] > zero else zero
            # censored readings: the uncensored neighbours are the darker ones (and those
            # consistent with the bound the brighter): the cell's own readings alone
            value = max(max(m[j], b[j]) if b[j] > zero else smoothed, zero)
            row[j] = value
            # measured: an uncensored reading in the cell, or (a cell at the frame's edge
            # without the channel's pixels) none censored and some around
            measured = (n[j] > zero) | ((b[j] <= zero) & (den[j] > zero))
            brightest[j] = max(brightest[j], value * inverse if measured else none)
    for c in range(3):  # clipped channels at least the white-balanced level of the measured ones
        n, b, den, row, level = info[c, i], bound[c, i], denominator[c, i], out[c, o], white[c]
        for j in range(row.size):
            measured = (n[j] > zero) | ((b[j] <= zero) & (den[j] > zero))
            value = row[j]
            row[j] = value if measured else max(value, level * brightest[j])
    red, green, blue = out[0, o], out[1, o], out[2, o]
    w0, w1, w2 = white[0], white[1], white[2]
    for j in range(red.size):  # every channel only a bound: neutral white at the largest
        r, g, bl = red[j], green[j], blue[j]
        top = max(r / w0, max(g / w1, bl / w2))
        bounded = brightest[j] < zero
        red[j] = w0 * top if bounded else r
        green[j] = w1 * top if bounded else g
        blue[j] = w2 * top if bounded else bl
