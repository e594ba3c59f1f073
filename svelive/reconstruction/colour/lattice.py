"""Channels of saturated colour from their own lattices (svelive.reconstruction.colour, step c''): where a
pixel's own CFA channel carries almost none of its colour's light, its other channels are interpolated
from their own sites around it (log-bilinear over the 3x3), not taken as Y k_c (:func:`lattice_channels`).

Why. Step b folds each channel's share into its pixels' exposure, e' = e k_c. On a saturated colour (a
red surface, a green light) the other channels' shares are near the floor, so their pixels' readings say
next to nothing about the luminance: their Y is the mono method's interpolation from the colour's own
sites, with the window the method chooses from evidence those pixels cannot give (their own reading is
noise). Fine detail of that colour goes: dark rings 2 px wide on a red disc (the shared BrightRings
image) came out as a flat red with a dot at each red site (diagnosis in docs/peers.md). Interpolating
each channel on its own lattice keeps what the lattice resolves there, as a demosaicing does; in the
logarithm, so that a step of a thousand to one is not smeared over its dark side.

Where. The pixel's own channel's share of its brightest one, f = k_own / max_c k_c (from the cells'
shares, as folded): its reading holds about f^2 (read-noise regime) to f (shot-noise regime) of the
information a pixel of the brightest channel holds there. Below F_LOW (1 % to 10 %) its value is an
interpolation anyway, and the other channels become the lattice's; from F_LOW to F_HIGH the two are
blended linearly; above F_HIGH (the pixel's own reading weighs in), Y k_c stays. Where every cell
around has all its shares within F_HIGH of its largest (every scene without strongly saturated colour),
nothing changes: cells are tested first, and only pixel rows near a flagged cell are visited.

Each pixel keeps its own channel (Y k_own); the luminance becomes sum_c n_c RGB_c where a pixel changed.
2x2 Bayer CFAs only (other CFAs are left as they are). A single frame's joint colour runs it after
colourising (joint_parts.joint), a stream after colouring its fused luminance with its fused shares
(svelive.reconstruction.stream).
"""

from __future__ import annotations

from concurrent.futures import Executor

import cv2
import numpy as np

from svelive.jit import kernel
from svelive.reconstruction.colour.cells import CellLayout
from svelive.reconstruction.colour.interpolate import _pieces
from svelive.reconstruction.colour.sites import applies
from svelive.reconstruction.methods.base import SveInput, map_on

#: Below this share of its brightest channel, a pixel's other channels are those of their lattices.
F_LOW = 0.1
#: Above this share, a pixel keeps Y k_c; between F_LOW and F_HIGH the two are blended linearly.
F_HIGH = 0.3


def flagged_cells(shares: np.ndarray, high: float = F_HIGH) -> np.ndarray:
    """uint8 (Hc, Wc): 1 within one cell of a cell whose smallest share is below ``high`` times its
    largest, from the cells' shares (3, Hc, Wc). A pixel between four unflagged cells has every
    channel's share at least ``high`` times its largest (a bilinear mean of cells where that holds)."""
    low = np.empty(shares.shape[1:], np.uint8)
    _low_cells(np.ascontiguousarray(shares, np.float32), np.float32(high), low)
    return cv2.dilate(low, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)


@kernel
def _low_cells(shares, high, out):
    """out (Hc, Wc) uint8 = 1 where the smallest of a cell's shares (3, Hc, Wc) is below ``high`` times its
    largest (float32), else 0: one pass instead of numpy's five over the planes."""
    for i in range(out.shape[0]):
        r, g, b, o = shares[0, i], shares[1, i], shares[2, i], out[i]
        for j in range(o.size):
            o[j] = np.uint8(min(min(r[j], g[j]), b[j]) < high * max(max(r[j], g[j]), b[j]))


def lattice_channels(inp: SveInput, luminance: np.ndarray, rgb: np.ndarray, shares: np.ndarray,
                     layout: CellLayout, workers: int | Executor = 1, finite: np.ndarray | None = None) -> bool:
    """Saturated colour's channels from their own lattices (module docstring) into ``rgb`` (float32
    (H, W, 3), Y k_c) and ``luminance`` (float32 (H, W), Y), in place. ``shares``: the cells' shares
    (3, Hc, Wc) of ``layout``'s cells (its nominal exposures give the log's floor: the longest
    exposure's noise floor). Returns False (nothing done) where it does not apply (not a 2x2 Bayer
    CFA, a frame under 3x3). ``finite``: bool (H,) or None: set False on the rows where a value it writes into
    ``rgb`` is not finite (refine's flags, kept valid for what this changes)."""
    h, w = inp.shape
    if not applies(inp.cfa) or h < 3 or w < 3 or inp.channels is None:
        return False
    f32 = np.float32
    flags = flagged_cells(shares)
    (cy, cx), exposures = layout.cell, layout.exposures
    wc = flags.shape[1]
    # the flagged cells' flat indices, row by row: the kernel visits them alone (a scan of every cell of the rows
    # with one flagged was most of its time where a few cells of most rows are flagged)
    cells = np.flatnonzero(flags.view(bool))  # (0 or 1: as bool, numpy finds them 7 times faster)
    floor = f32(np.sqrt(inp.sensor.floor_variance) / float(np.max(exposures)))
    weights = np.asarray(layout.share, f32)
    checked = np.empty(0, np.bool_) if finite is None else finite

    def piece(part: slice) -> None:
        lo, hi = np.searchsorted(cells, [part.start // cy * wc, -(-part.stop // cy) * wc])
        _lattice(rgb, luminance, inp.channels, inp.censored, cells[lo:hi], wc, cy, cx, weights, floor, f32(F_LOW),
                 f32(F_HIGH), part.start, part.stop, checked)

    map_on(workers, piece, _pieces(h))
    return True


@kernel
def _lattice(rgb, luminance, channels, censored, cells, wc, cy, cx, share, floor, low, high, first, last, finite):
    """Rows ``first`` to ``last`` (the frame's outer rows and columns excepted) of
    :func:`lattice_channels`, in place: at each pixel of a flagged cell (``cells``: their flat indices
    into the (Hc, ``wc``) cells, in any order) whose own channel's share of its largest, f, is below
    ``high``, each other channel c moves by w = min((high - f) / (high - low), 1) towards the geometric
    mean of V + floor over the pixels of channel c in its 3x3, minus ``floor`` (V their own channel's
    value; on a Bayer tile a channel's pixels in a 3x3 are all at its sides or all at its corners, so
    this is the log-bilinear interpolation; products of four HDR values in float64), and the luminance
    is sum_c n_c RGB_c.
    Not where the pixel or one of its 3x3 is ``censored`` (a bound: the cells' highlight rules stay).
    Only the pixels' own channels are read around a pixel, which no pixel writes (rows of other
    threads' pieces included). ``finite`` (H,) bool, unless empty: set False on a row where a value
    written is not finite."""
    h, w = luminance.shape
    zero, one = np.float32(0.0), np.float32(1.0)
    span = high - low
    flagged = finite.size > 0
    for index in range(cells.size):
        i, j = cells[index] // wc, cells[index] % wc
        for r in range(max(i * cy, first, 1), min(i * cy + cy, last, h - 1)):
            ch, up = channels[r], channels[r - 1]
            for x in range(max(j * cx, 1), min(j * cx + cx, w - 1)):
                own = ch[x]
                top = max(rgb[r, x, 0], max(rgb[r, x, 1], rgb[r, x, 2]))
                f = rgb[r, x, own] / top if top > zero else high
                if f >= high or _any_censored(censored, r, x):
                    continue
                weight = min((high - f) / span, one)
                if own == 1:  # a green pixel: one channel at its sides along the row, the other along the column
                    a, b = ch[x - 1], up[x]
                    va = np.sqrt(_plus(rgb[r, x - 1, a], floor) * _plus(rgb[r, x + 1, a], floor))
                    vb = np.sqrt(_plus(rgb[r - 1, x, b], floor) * _plus(rgb[r + 1, x, b], floor))
                else:  # red or blue: green at its four sides, the other at its four corners
                    a, b = np.uint8(1), up[x - 1]
                    va = np.sqrt(np.sqrt(_plus(rgb[r, x - 1, a], floor) * _plus(rgb[r, x + 1, a], floor)
                                         * _plus(rgb[r - 1, x, a], floor) * _plus(rgb[r + 1, x, a], floor)))
                    vb = np.sqrt(np.sqrt(_plus(rgb[r - 1, x - 1, b], floor) * _plus(rgb[r - 1, x + 1, b], floor)
                                         * _plus(rgb[r + 1, x - 1, b], floor) * _plus(rgb[r + 1, x + 1, b], floor)))
                pa, pb = rgb[r, x, a], rgb[r, x, b]
                pa += weight * (max(np.float32(va) - floor, zero) - pa)
                pb += weight * (max(np.float32(vb) - floor, zero) - pb)
                rgb[r, x, a], rgb[r, x, b] = pa, pb
                if flagged and not (np.isfinite(pa) and np.isfinite(pb)):
                    finite[r] = False
                luminance[r, x] = share[own] * rgb[r, x, own] + share[a] * pa + share[b] * pb


@kernel(inline="always")
def _plus(value, floor):
    """max(value, 0) + floor as float64 (a factor of :func:`_lattice`'s products)."""
    return np.float64(max(value, np.float32(0.0)) + floor)


@kernel(inline="always")
def _any_censored(censored, r, x):
    """Whether a pixel of the 3x3 around (r, x) is censored."""
    for rr in range(r - 1, r + 2):
        for xx in range(x - 1, x + 2):
            if censored[rr, xx]:
                return True
    return False
