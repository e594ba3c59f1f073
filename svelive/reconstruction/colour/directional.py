"""Directional demosaicing of the joint colour's own site values (svelive.reconstruction.colour, step c'''):
each pixel keeps its own CFA channel, and its other two channels come from a demosaicing of every pixel's
own channel with directional filtering and a posteriori decision (Menon, Andriani, Calvagno, IEEE TIP
16(1), 2007), run on the logarithm of the values (:func:`directional_channels`, :func:`demosaic_log`).

Why. The cells hold the chroma of 4x2 pixels (dual-ISO): at edges and in colour texture the other
channels are Y k_c with the cells' shares, which blur colour across the edge. A pixel's own reading and
its neighbours' carry the colour at the resolution of the CFA; a demosaicer that interpolates green
along the edge, not across it, and the colour differences after it, recovers the other channels there
(issue 27, docs/peers.md: +0.05 to +1.5 dB over all channels on the peer frames). In the logarithm the
colour differences are log ratios, so a step of a thousand to one is not smeared over its dark side.

The demosaicing (:func:`demosaic_log`, on a 2x2 Bayer mosaic of log values):

1. green at the red and blue sites along rows and along columns: the mean of the two greens beside the
   site plus half the site's own channel's second difference, (2 X(0) - X(-2) - X(+2)) / 4;
2. the decision: the colour difference X - G of each direction at the red and blue sites, its gradient
   between sites two apart along the direction, summed over the 5x5 window around the pixel (the centre
   row or column weighted 3); rows win where the columns' sum is at least the rows';
3. red and blue at the green sites: green plus the mean of X - G over the two sites of X beside it;
   red at blue sites (and blue at red): the site's value plus the mean of R - B over its two green
   neighbours along the chosen direction;
4. the refinement: the colour differences smoothed over three pixels along the chosen direction (green
   at red and blue sites, and red and blue at each other's sites) or over the two sites beside a green
   pixel (red and blue there).

It runs on the four quarter planes of the mosaic (:class:`Grid`: red sites, greens of red rows, greens
of blue rows, blue sites, each (H/2, W/2)), so each step is a branch-free kernel over neighbours at
fixed offsets, which vectorises; the padding of each plane is the frame mirrored about its edge pixel,
refreshed after each step. Sums feeding the decision are taken in the order (and with the fused
multiply-adds) of the OpenCV filters of the first, full-resolution version, so that near-ties fall the
same way (the output is bit for bit that version's).

Where. A strongly saturated colour's other channels are the lattice stage's (colour.lattice): the
demosaicer's green-guided differences fail where green reads noise. So the weight of the demosaiced
channels is the lattice stage's blend turned round: 0 where the smallest share of its own channel of
the brightest one, f, over the pixel's 3x3 is below F_LOW, 1 above F_HIGH, linear between; times the
mean over 5x5 of each site's m^2 / (m^2 + v), its reading's signal-to-noise weight (v from the noise
model at its own exposure, m its value): noise-dominated readings leave the cells' chroma. Pixels within
one pixel of a censored reading keep today's channels (the highlight rules stay: no magenta). The
logarithm's floor is the longest exposure's read-noise floor, as the lattice stage's.

2x2 Bayer CFAs only (others untouched). Each pixel keeps its own channel; the luminance becomes
sum_c n_c RGB_c where a pixel changed.
"""

from __future__ import annotations

from concurrent.futures import Executor

import cv2
import numpy as np

from svelive.jit import flat, kernel
from svelive.reconstruction.colour.cells import CellLayout
from svelive.reconstruction.colour.interpolate import _pieces
from svelive.reconstruction.colour.lattice import F_HIGH, F_LOW
from svelive.reconstruction.colour.sites import applies
from svelive.reconstruction.methods.base import SveInput, map_on

#: Planes of the padded mosaic, by (row, column) parity: red, green on red rows, green on blue rows, blue.
R, GR, GB, B = 0, 1, 2, 3
PARITY = ((0, 0), (0, 1), (1, 0), (1, 1))


class Grid:
    """The quarter planes of an (H, W) Bayer mosaic with red at ``red``: the mosaic padded so that red sits
    at even rows and columns (top ``top`` = 2 + red row, left ``left`` = 2 + red column, at least 2 more
    at the bottom and right, even height and width), each plane (hq, wq) holding the pixels of one parity
    (PARITY). Pixel (y, x) of the frame is plane 2 (Y % 2) + X % 2 at (Y // 2, X // 2), Y = y + top,
    X = x + left. Padding is the frame mirrored about its edge pixels (:meth:`mirror`)."""

    def __init__(self, shape: tuple[int, int], red: tuple[int, int]):
        self.h, self.w = shape
        self.top, self.left = 2 + red[0], 2 + red[1]
        self.hq, self.wq = (self.top + self.h + 4) // 2, (self.left + self.w + 4) // 2
        self._rows = [self._edges(self.top, self.h, p, self.hq) for p in (0, 1)]
        self._cols = [self._edges(self.left, self.w, p, self.wq) for p in (0, 1)]

    @staticmethod
    def _edges(start: int, n: int, parity: int, size: int) -> tuple[np.ndarray, np.ndarray]:
        """(padding indices, their mirror sources) of one parity's plane along one axis."""
        full = 2 * np.arange(size) + parity
        inside = (full >= start) & (full < start + n)
        mirrored = np.where(full < start, 2 * start - full, 2 * (start + n - 1) - full)
        source = np.clip((mirrored - parity) // 2, np.flatnonzero(inside)[0], np.flatnonzero(inside)[-1])
        pad = np.flatnonzero(~inside)
        return pad, source[pad]

    def planes(self, count: int, dtype=np.float32) -> np.ndarray:
        """An uninitialised (count, hq, wq) stack of planes."""
        return np.empty((count, self.hq, self.wq), dtype)

    def mirror(self, plane: np.ndarray, kind: int) -> None:
        """Fill the padding of a plane of ``kind`` (R, GR, GB, B) with its mirrored pixels, in place."""
        py, px = PARITY[kind]
        (rows, rsrc), (cols, csrc) = self._rows[py], self._cols[px]
        plane[rows] = plane[rsrc]
        plane[:, cols] = plane[:, csrc]

    def zero(self, plane: np.ndarray, kind: int) -> None:
        """Set the padding of a plane of ``kind`` to 0, in place."""
        plane[self._rows[PARITY[kind][0]][0]] = 0
        plane[:, self._cols[PARITY[kind][1]][0]] = 0

    def split(self, image: np.ndarray, out: np.ndarray) -> None:
        """Frame (H, W) -> its four planes ``out`` (4, hq, wq) with mirrored padding."""
        for kind, (py, px) in enumerate(PARITY):
            y0, x0 = (self.top + py) % 2, (self.left + px) % 2  # the frame's first row/column of this parity
            i0, j0 = (self.top + y0) // 2, (self.left + x0) // 2
            part = image[y0::2, x0::2]
            out[kind, i0:i0 + part.shape[0], j0:j0 + part.shape[1]] = part
            self.mirror(out[kind], kind)


@kernel
def _green(m, gh, gv, first, last):
    """Step 1 on quarter rows ``first`` to ``last`` (columns 1 to wq - 2): green along the rows (``gh``)
    and the columns (``gv``) at the red (gh[0], gv[0]) and blue (gh[1], gv[1]) sites of the planes ``m``
    (4, hq, wq): half the site plus half the two greens beside it minus a quarter of the two own sites two
    pixels away (OpenCV's order of the sums, so that the decision's ties fall as before)."""
    half, quarter = np.float32(0.5), np.float32(-0.25)
    r, gr, gb, b = m[0], m[1], m[2], m[3]
    for i in range(first, last):
        for j in range(1, m.shape[2] - 1):
            gh[0, i, j] = r[i, j] * half + (gr[i, j - 1] + gr[i, j]) * half + (r[i, j - 1] + r[i, j + 1]) * quarter
            gv[0, i, j] = r[i, j] * half + (gb[i - 1, j] + gb[i, j]) * half + (r[i - 1, j] + r[i + 1, j]) * quarter
            gh[1, i, j] = b[i, j] * half + (gb[i, j] + gb[i, j + 1]) * half + (b[i, j - 1] + b[i, j + 1]) * quarter
            gv[1, i, j] = b[i, j] * half + (gr[i, j] + gr[i + 1, j]) * half + (b[i - 1, j] + b[i + 1, j]) * quarter


@kernel
def _gradients(m, gh, gv, d, first, last):
    """Step 2's gradients: ``d`` (4, hq, wq) = |C(x) - C(x + 2)| of C = X - G along the rows at red (d[0])
    and blue (d[2]) sites, along the columns (d[1], d[3])."""
    for k in range(2):
        x = m[3 * k]
        for i in range(first, last):
            for j in range(1, m.shape[2] - 1):
                d[2 * k, i, j] = abs((x[i, j] - gh[k, i, j]) - (x[i, j + 1] - gh[k, i, j + 1]))
                d[2 * k + 1, i, j] = abs((x[i, j] - gv[k, i, j]) - (x[i + 1, j] - gv[k, i + 1, j]))


@kernel(fastmath={"contract"})
def _decide(d, gh, gv, horizontal, first, last):
    """Step 2's decision at the red and blue sites: the window sums of the gradients ``d`` (module docstring;
    summed in the order of OpenCV's filter2D over the full-resolution window); green along the rows
    (``gh``, written in place, ``horizontal`` 1) where the columns' sum is at least the rows', else ``gv``."""
    hr, vr, hb, vb = d[0], d[1], d[2], d[3]
    three = np.float32(3.0)
    for i in range(first, last):
        for j in range(1, d.shape[2] - 1):
            s = hr[i - 1, j - 1] + hr[i - 1, j] + hb[i - 1, j - 1]
            s = three * hr[i, j] + (three * hr[i, j - 1] + s)
            rows = s + hb[i, j - 1] + hr[i + 1, j - 1] + hr[i + 1, j]
            s = (three * vr[i - 1, j] + vr[i - 1, j - 1]) + vr[i - 1, j + 1] + vb[i - 1, j - 1] + vb[i - 1, j] + vr[i, j - 1]
            cols = three * vr[i, j] + s + vr[i, j + 1]
            along = cols >= rows
            horizontal[0, i, j] = along
            gh[0, i, j] = gh[0, i, j] if along else gv[0, i, j]
            s = hb[i - 1, j - 1] + hb[i - 1, j] + hr[i, j]
            s = three * hb[i, j] + (three * hb[i, j - 1] + s)
            rows = s + hr[i + 1, j] + hb[i + 1, j - 1] + hb[i + 1, j]
            s = (three * vb[i - 1, j] + vb[i - 1, j - 1]) + vb[i - 1, j + 1] + vr[i, j] + vr[i, j + 1] + vb[i, j - 1]
            cols = three * vb[i, j] + s + vb[i, j + 1]
            along = cols >= rows
            horizontal[1, i, j] = along
            gh[1, i, j] = gh[1, i, j] if along else gv[1, i, j]


@kernel
def _at_green(m, g, out, first, last):
    """Step 3 at the green sites: ``out`` (4, hq, wq) = red and blue at the greens of red rows (out[0],
    out[1]) and of blue rows (out[2], out[3]): green plus the mean of X - G (``g``: green at the red and
    blue sites) over the two X sites beside it."""
    half = np.float32(0.5)
    r, gr, gb, b, gre, gbl = m[0], m[1], m[2], m[3], g[0], g[1]
    for i in range(first, last):
        for j in range(1, m.shape[2] - 1):
            out[0, i, j] = gr[i, j] + half * ((r[i, j] - gre[i, j]) + (r[i, j + 1] - gre[i, j + 1]))
            out[1, i, j] = gr[i, j] + half * ((b[i - 1, j] - gbl[i - 1, j]) + (b[i, j] - gbl[i, j]))
            out[2, i, j] = gb[i, j] + half * ((r[i, j] - gre[i, j]) + (r[i + 1, j] - gre[i + 1, j]))
            out[3, i, j] = gb[i, j] + half * ((b[i, j - 1] - gbl[i, j - 1]) + (b[i, j] - gbl[i, j]))


@kernel
def _at_opposite(m, greens, horizontal, other, centre, first, last):
    """Step 3 (``centre`` 0) and the refinement (1) at the red and blue sites: ``other`` (2, hq, wq), blue at
    the red sites and red at the blue ones: the site's value minus (plus) the mean of R - B over its two
    green neighbours along the chosen direction (``greens``: :func:`_at_green`'s planes) and, with weight
    ``centre``, the site's own R - B (its ``other`` from step 3)."""
    r, b, rgr, bgr, rgb, bgb = m[0], m[3], greens[0], greens[1], greens[2], greens[3]
    scale = np.float32(2.0) + centre
    for i in range(first, last):
        for j in range(1, m.shape[2] - 1):
            rows = (rgr[i, j - 1] - bgr[i, j - 1]) + (rgr[i, j] - bgr[i, j])
            cols = (rgb[i - 1, j] - bgb[i - 1, j]) + (rgb[i, j] - bgb[i, j])
            diff = (rows if horizontal[0, i, j] else cols) + centre * (r[i, j] - other[0, i, j])
            other[0, i, j] = r[i, j] - diff / scale
            rows = (rgb[i, j] - bgb[i, j]) + (rgb[i, j + 1] - bgb[i, j + 1])
            cols = (rgr[i, j] - bgr[i, j]) + (rgr[i + 1, j] - bgr[i + 1, j])
            diff = (rows if horizontal[1, i, j] else cols) + centre * (other[1, i, j] - b[i, j])
            other[1, i, j] = b[i, j] + diff / scale


@kernel
def _refine_green(m, greens, horizontal, g, first, last):
    """The refinement of green at the red and blue sites (``g``, in place): the site's value minus the
    three-pixel mean of X - G along the chosen direction."""
    third = np.float32(1.0 / 3.0)
    r, gr, gb, b, rgr, bgr, rgb, bgb = m[0], m[1], m[2], m[3], greens[0], greens[1], greens[2], greens[3]
    for i in range(first, last):
        for j in range(1, m.shape[2] - 1):
            rows = (rgr[i, j - 1] - gr[i, j - 1]) + (rgr[i, j] - gr[i, j])
            cols = (rgb[i - 1, j] - gb[i - 1, j]) + (rgb[i, j] - gb[i, j])
            g[0, i, j] = r[i, j] - third * ((rows if horizontal[0, i, j] else cols) + (r[i, j] - g[0, i, j]))
            rows = (bgb[i, j] - gb[i, j]) + (bgb[i, j + 1] - gb[i, j + 1])
            cols = (bgr[i, j] - gr[i, j]) + (bgr[i + 1, j] - gr[i + 1, j])
            g[1, i, j] = b[i, j] - third * ((rows if horizontal[1, i, j] else cols) + (b[i, j] - g[1, i, j]))


def demosaic_grid(grid: Grid, m: np.ndarray, refine: bool = True, workers: int | Executor = 1):
    """The demosaicing on the planes ``m`` (4, hq, wq, float32, mirrored padding) of ``grid``. Returns
    (g, greens, other): green at the red and blue sites (2, hq, wq), red and blue at the greens of red rows
    and of blue rows (4, hq, wq), blue at the red sites and red at the blue ones (2, hq, wq); valid inside
    the frame."""
    gh, gv, d = grid.planes(2), grid.planes(2), np.zeros((4, grid.hq, grid.wq), np.float32)
    horizontal, other = grid.planes(2, np.uint8), np.zeros((2, grid.hq, grid.wq), np.float32)
    pieces = _pieces(grid.hq - 2)

    def run(function, *args):
        map_on(workers, lambda part: function(*args, part.start + 1, part.stop + 1), pieces)

    run(_green, m, gh, gv)
    for k, kind in enumerate((R, B)):
        grid.mirror(gh[k], kind)
        grid.mirror(gv[k], kind)
    run(_gradients, m, gh, gv, d)
    for k, kind in enumerate((R, R, B, B)):
        grid.zero(d[k], kind)
    run(_decide, d, gh, gv, horizontal)
    g, greens = gh, d  # (the gradients are spent)
    for step in range(2 if refine else 1):
        if step:
            run(_refine_green, m, greens, horizontal, g)
        for k, kind in enumerate((R, B)):
            grid.mirror(g[k], kind)
        run(_at_green, m, g, greens)
        for k, kind in enumerate((GR, GR, GB, GB)):
            grid.mirror(greens[k], kind)
        run(_at_opposite, m, greens, horizontal, other, np.float32(step))
    return g, greens, other


def demosaic_log(mosaic: np.ndarray, red: tuple[int, int], refine: bool = True) -> np.ndarray:
    """Menon et al.'s directional demosaicing (module docstring) of a 2x2 Bayer mosaic.

    Args:
        mosaic: float32 (H, W), each pixel's own channel (any unit; the svelive stage gives logarithms),
            H and W at least 3.
        red: (row, column) of the red site in the 2x2 tile; blue is at the other parity of both.
        refine: the refinement step (4).

    Returns:
        float32 (H, W, 3) R, G, B, each pixel's own channel equal to ``mosaic``; borders mirrored about
        the edge pixel.
    """
    grid = Grid(mosaic.shape, red)
    m = grid.planes(4)
    grid.split(np.asarray(mosaic, np.float32), m)
    g, greens, other = demosaic_grid(grid, m, refine)
    # each kind of site's R, G, B planes
    sources = ((m[R], g[0], other[0]), (greens[0], m[GR], greens[1]), (greens[2], m[GB], greens[3]),
               (other[1], g[1], m[B]))
    full = np.empty((2 * grid.hq, 2 * grid.wq, 3), np.float32)
    for (py, px), planes in zip(PARITY, sources):
        full[py::2, px::2] = np.stack(planes, axis=-1)
    return full[grid.top:grid.top + grid.h, grid.left:grid.left + grid.w].copy()


@kernel(inline="always")
def _run(y, x0, top, left, w):
    """The pixels of frame row ``y`` at columns x0, x0 + 2, ... (one kind of site) in the quarter planes
    of a grid with padding ``top``, ``left``: (kind, plane row, first plane column, count)."""
    return 2 * ((y + top) % 2) + (x0 + left) % 2, (y + top) // 2, (x0 + left) // 2, (w - x0 + 1) // 2


@kernel
def _site_terms(rgb, exposure, inverse_gain, floor_variance, floor, top, left, m, share, snr, first, last):
    """Rows ``first`` to ``last`` of the frame: each pixel's own channel's value V (of ``rgb``, float32
    (H, W, 3)), its share of its brightest channel (``share``, 1 where all are 0), V^2 / (V^2 + v) (``snr``;
    v = (e V / g + floor variance) / e^2 the noise model's variance at its exposure e), and max(V, 0) +
    ``floor`` into the planes ``m`` (4, hq, wq) of the grid with padding ``top``, ``left``."""
    zero, one = np.float32(0.0), np.float32(1.0)
    w = share.shape[1]
    for y in range(first, last):
        for x0 in range(2):
            kind, i, j0, n = _run(y, x0, top, left, w)
            channel = 0 if kind == 0 else 2 if kind == 3 else 1
            plane = m[kind, i]
            for k in range(n):
                x = x0 + 2 * k
                v = rgb[y, x, channel]
                brightest = max(rgb[y, x, 0], max(rgb[y, x, 1], rgb[y, x, 2]))
                share[y, x] = v / brightest if brightest > zero else one
                level = max(v, zero)
                e = exposure[y, x]
                variance = (e * level * inverse_gain + floor_variance) / (e * e)
                snr[y, x] = level * level / (level * level + variance)
                plane[j0 + k] = level + floor


@kernel
def _weights(smallest, snr_mean, near, low, scale, weight):
    """The weight (module docstring, Where) from the 3x3's smallest share, the 5x5 mean of the sites'
    signal-to-noise weights and the censored neighbourhoods (flat float32 / uint8 arrays). Returns the
    count of nonzero weights."""
    zero, one = np.float32(0.0), np.float32(1.0)
    count = 0
    for k in range(weight.size):
        wt = min(max((smallest[k] - low) * scale, zero), one) * snr_mean[k]
        wt = zero if near[k] else wt
        weight[k] = wt
        count += wt > zero
    return count


@kernel
def _blend(rgb, luminance, weight, exps, floor, share, top, left, first, last):
    """Rows ``first`` to ``last``: at each pixel of nonzero ``weight``, its other two channels move by the
    weight towards exp of their demosaiced logarithms minus ``floor`` (at least 0; ``exps``: (8, hq, wq),
    the exponentials of green and blue at red sites, red and blue at the greens of red rows, of blue rows,
    red and green at blue sites), and the luminance becomes sum_c n_c RGB_c."""
    zero = np.float32(0.0)
    w = luminance.shape[1]
    for y in range(first, last):
        row, lum, wts = rgb[y], luminance[y], weight[y]
        for x0 in range(2):
            kind, i, j0, n = _run(y, x0, top, left, w)
            c1 = 1 if kind == 0 else 0
            c2 = 1 if kind == 3 else 2
            a, b = exps[2 * kind, i], exps[2 * kind + 1, i]
            for k in range(n):  # branch-free (selects), so that it vectorises
                x = x0 + 2 * k
                wt = wts[x]
                p = row[x]
                p1 = p[c1] + wt * (max(a[j0 + k] - floor, zero) - p[c1])
                p2 = p[c2] + wt * (max(b[j0 + k] - floor, zero) - p[c2])
                moved = wt > zero
                p[c1] = p1 if moved else p[c1]
                p[c2] = p2 if moved else p[c2]
                y_new = share[0] * p[0] + share[1] * p[1] + share[2] * p[2]
                lum[x] = y_new if moved else lum[x]


def log_floor(inp: SveInput, layout: CellLayout) -> float:
    """The logarithm's floor (DN at exposure 1): the longest exposure's read-noise floor, as the lattice
    stage's."""
    return float(np.sqrt(inp.sensor.floor_variance) / float(np.max(layout.exposures)))


def red_site(inp: SveInput) -> tuple[int, int] | None:
    """(row, column) of red in ``inp``'s 2x2 Bayer tile, or None where the stage does not apply."""
    if not applies(inp.cfa):
        return None
    tile = inp.cfa.tile
    y, x = np.argwhere(tile == 0)[0]
    return int(y), int(x)


def directional_channels(inp: SveInput, luminance: np.ndarray, rgb: np.ndarray, share: np.ndarray,
                         floor: float, refine: bool = True, workers: int | Executor = 1) -> bool:
    """The stage (module docstring) into ``rgb`` (float32 (H, W, 3), linear, DN at exposure 1) and
    ``luminance`` (float32 (H, W), Y), in place. ``share``: n_c of the CFA. ``floor``: the logarithm's
    floor (DN at exposure 1; the longest exposure's read-noise floor). Each pixel keeps its own channel.
    ``workers``: threads for its pieces of rows (base.map_on); the result does not depend on it.
    Returns False (nothing done) where it does not apply (not a 2x2 Bayer CFA, a frame under 5x5)."""
    h, w = luminance.shape
    red = red_site(inp)
    if red is None or h < 5 or w < 5 or inp.channels is None:
        return False
    f32 = np.float32
    grid = Grid((h, w), red)
    m = grid.planes(4)
    weight = _site_weights(inp, rgb, grid, m, f32(floor), workers)
    if weight is None:
        return True
    g, greens, other = demosaic_grid(grid, m, refine, workers)
    # the demosaiced channels of each kind of site, in _blend's order
    exps = np.stack([g[0], other[0], greens[0], greens[1], greens[2], greens[3], other[1], g[1]])
    cv2.exp(exps.reshape(-1, grid.wq), exps.reshape(-1, grid.wq))
    n = np.asarray(share, f32)
    map_on(workers, lambda part: _blend(rgb, luminance, weight, exps, f32(floor), n, grid.top, grid.left,
                                        part.start, part.stop), _pieces(h))
    return True


def _site_weights(inp: SveInput, rgb: np.ndarray, grid: Grid, m: np.ndarray, floor: np.float32,
                  workers: int | Executor) -> np.ndarray | None:
    """float32 (H, W): the demosaiced channels' weight (module docstring, Where), or None where it is 0
    everywhere; ``m`` (4, hq, wq) filled with the logarithms of the sites' values plus ``floor``."""
    f32 = np.float32
    h, w = grid.h, grid.w
    share, snr = np.empty((h, w), f32), np.empty((h, w), f32)
    sensor = inp.sensor
    exposure = np.asarray(inp.exposure, f32)
    map_on(workers, lambda part: _site_terms(rgb, exposure, f32(1.0 / sensor.effective_gain),
                                             f32(sensor.floor_variance), floor, grid.top, grid.left, m, share,
                                             snr, part.start, part.stop), _pieces(h))
    smallest = cv2.erode(share, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)
    snr_mean = cv2.blur(snr, (5, 5), dst=snr, borderType=cv2.BORDER_REFLECT)
    near = cv2.dilate(inp.censored.view(np.uint8), np.ones((3, 3), np.uint8))
    weight = share  # (the shares are spent)
    if _weights(*flat(smallest, snr_mean, near), f32(F_LOW), f32(1.0 / (F_HIGH - F_LOW)), flat(weight)[0]) == 0:
        return None
    planes = m.reshape(-1, grid.wq)
    cv2.log(planes, planes)
    for kind in range(4):
        grid.mirror(m[kind], kind)
    return weight
