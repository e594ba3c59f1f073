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
of blue rows, blue sites, each (H/2, W/2)), so each step is a branch-free loop over neighbours at fixed
offsets, which vectorises; the padding of each plane is the frame mirrored about its edge pixel. The steps
are streamed (:func:`_advance`): each step's rows live in a ring of a few rows, and step k computes plane
row r once step k - 1 has computed row r + LAG, so the planes between steps stay in cache instead of going
through memory a whole plane at a time; a row outside the frame is read from its mirror source. The stage
exponentiates and blends each chunk of rows as it comes out. Sums feeding the decision are taken in the
order (and with the fused multiply-adds) of the OpenCV filters of the first, full-resolution version, so
that near-ties fall the same way (the output is bit for bit that version's).

Where. A strongly saturated colour's other channels are the lattice stage's (colour.lattice): the
demosaicer's green-guided differences fail where green reads noise. So the weight of the demosaiced
channels is the lattice stage's blend turned round: 0 where the smallest share of its own channel of
the brightest one, f, over the pixel's 3x3 is below F_LOW, 1 above F_HIGH, linear between; times the
mean over 5x5 of each site's m^2 / (m^2 + v), its reading's signal-to-noise weight (v from the noise
model at its own exposure, m its value; 0 at a censored reading, whose value is a fill: nothing is measured
there): noise-dominated readings and fills leave the cells' chroma in proportion. Pixels within
one pixel of a clipped reading (censored, with no uncensored reading of its channel in its 5x5: the channel
clipped there) keep today's channels (the highlight rules stay: no magenta); a censored long reading beside
uncensored short ones of its channel holds the fill, a value, and is demosaiced (docs/peers.md: Cannon and
MtTamWest bright +0.3 and +0.1 dB over the gate on every censored reading). The logarithm's floor is the
longest exposure's read-noise floor, as the lattice stage's.

Only where there is colour texture. In tiles (CHUNK plane rows by TILE plane columns: 64 x 32 pixels) whose
mean of 2 |U - M| / (U + M) is at most TEXTURE (U a pixel's value of its row neighbours' channel from the
cells, M the mean of those neighbours' own values, both plus the floor: the cells' colour against the
readings beside it), the demosaicing would only repeat the cells' chroma, and the stage does nothing there.
A first pass over the frame sums the texture by row and tile (:func:`_texture_rows`); then each run of the
other tiles gets a block of the planes and its weight, computed on its columns with MARGIN more on each side
and the stages' rows (:func:`_block`: bit for bit the whole frame's inside the tiles; every block is made
before any pixel changes), and is demosaiced, exponentiated and blended. On the peer frames this keeps 0.97 of the
stage's gain (mean PU21 over all channels 27.273 -> 27.261) and runs on 26-100 % of their tiles; on the
1920x1200 demo frame (a photograph enlarged: smooth at the pixel scale) on 12 %.

2x2 Bayer CFAs only (others untouched). Each pixel keeps its own channel; the luminance becomes
sum_c n_c RGB_c where a pixel changed.
"""

from __future__ import annotations

from concurrent.futures import Executor

import cv2
import numpy as np

from svelive.jit import kernel
from svelive.reconstruction.colour.cells import CellLayout
from svelive.reconstruction.colour.interpolate import _pieces
from svelive.reconstruction.colour.lattice import F_HIGH, F_LOW
from svelive.reconstruction.colour.sites import applies
from svelive.reconstruction.methods.base import SveInput, map_on

#: Planes of the padded mosaic, by (row, column) parity: red, green on red rows, green on blue rows, blue.
R, GR, GB, B = 0, 1, 2, 3
PARITY = ((0, 0), (0, 1), (1, 0), (1, 1))
#: For each kind of site (R, GR, GB, B), the planes of the demosaicing's output (:func:`_advance`) holding its R, G, B
#: (-1: the site's own channel).
OUTPUTS = np.array([[-1, 0, 6], [2, -1, 3], [4, -1, 5], [7, 1, -1]], np.intp)


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
        #: intp (2, hq): each plane row's mirror source by row parity (itself inside the frame); bool
        #: (2, hq): whether inside
        self.rowsrc = np.tile(np.arange(self.hq), (2, 1))
        self.rowin = np.ones((2, self.hq), bool)
        for p, (pad, source) in enumerate(self._rows):
            self.rowsrc[p, pad], self.rowin[p, pad] = source, False
        self.sources = self.rowsrc.tolist()  # (the same as lists, for the stages' rows: :func:`_stage_rows`)
        #: intp (2, k): the padding columns and their mirror sources by column parity (``ncol`` of each)
        self.ncol = np.array([len(c[0]) for c in self._cols], np.intp)
        self.colpad, self.colsrc = np.zeros((2, self.ncol.max()), np.intp), np.zeros((2, self.ncol.max()), np.intp)
        for p, (pad, source) in enumerate(self._cols):
            self.colpad[p, :len(pad)], self.colsrc[p, :len(pad)] = pad, source
        reach = np.arange(1, self.hq - 1)
        lead = max(int((self.rowsrc[:, reach + step] - reach).max()) for step in (-1, 0, 1))
        assert lead <= LAG, "a mirror source beyond the streamed stages' lag"  # (frames of at least 3x3)

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

    def split(self, image: np.ndarray, out: np.ndarray) -> None:
        """Frame (H, W) -> its four planes ``out`` (4, hq, wq) with mirrored padding."""
        for kind, (py, px) in enumerate(PARITY):
            y0, x0 = (self.top + py) % 2, (self.left + px) % 2  # the frame's first row/column of this parity
            i0, j0 = (self.top + y0) // 2, (self.left + x0) // 2
            part = image[y0::2, x0::2]
            out[kind, i0:i0 + part.shape[0], j0:j0 + part.shape[1]] = part
            self.mirror(out[kind], kind)


#: Quarter rows between the stages of the streamed demosaicing (:func:`_advance`): a stage computes row r
#: once the stage before has computed row r + LAG, which covers its reach (rows r - 1 to r + 1) and the
#: mirror sources of the padding rows near the top (Grid.lead checks it).
LAG = 3
#: Rows held of each stage's planes (a ring; more than the distance between a row's writing and its last read).
RING = 16
#: Plane rows exponentiated and blended at a time (the streamed output's ring, (CHUNK, 8, wq)).
CHUNK = 32
#: Plane columns of a tile of the colour texture test (module docstring, Where); a tile is CHUNK plane rows high.
TILE = 16
#: Plane columns computed beyond a piece's tiles: the stages' reach (one column each) with room to spare.
MARGIN = 10
#: A tile's least mean colour texture (2 |U - M| / (U + M), :func:`_texture_row`) for the stage to run there.
TEXTURE = 0.03
#: Stages of the demosaicing: green along rows and columns, gradients, decision, red and blue at the greens,
#: at the opposite sites; with the refinement, green refined, red and blue at the greens and at the opposite
#: sites again.
STAGES, STAGES_UNREFINED = 8, 5


@kernel(inline="always")
def _slot(rowsrc, parity, r):
    """Ring slot of plane row ``r`` of a plane of row ``parity``: its mirror source's (Grid.rowsrc)."""
    return rowsrc[parity, r] % RING


@kernel(inline="always")
def _dslot(rowin, parity, r):
    """Ring slot of gradient row ``r`` of row ``parity``: its own inside the frame, else the zero row (RING)."""
    return r % RING if rowin[parity, r] else RING


@kernel(inline="always")
def _mirror_cols(row, pads, sources, count):
    """A ring row's padding columns from their mirror sources (Grid.colpad), in place."""
    for c in range(count):
        row[pads[c]] = row[sources[c]]


@kernel
def _green_row(m, i, gh, gv, s):
    """Step 1 at plane row ``i`` (columns 1 to wq - 2) into ring slot ``s``: green along the rows (``gh``) and
    the columns (``gv``) at the red (gh[0], gv[0]) and blue (gh[1], gv[1]) sites of the planes ``m`` (4, hq,
    wq): half the site plus half the two greens beside it minus a quarter of the two own sites two pixels
    away (OpenCV's order of the sums, so that the decision's ties fall as before)."""
    half, quarter = np.float32(0.5), np.float32(-0.25)
    r, gr, gb, b = m[0], m[1], m[2], m[3]
    for j in range(1, m.shape[2] - 1):
        gh[0, s, j] = r[i, j] * half + (gr[i, j - 1] + gr[i, j]) * half + (r[i, j - 1] + r[i, j + 1]) * quarter
        gv[0, s, j] = r[i, j] * half + (gb[i - 1, j] + gb[i, j]) * half + (r[i - 1, j] + r[i + 1, j]) * quarter
        gh[1, s, j] = b[i, j] * half + (gb[i, j] + gb[i, j + 1]) * half + (b[i, j - 1] + b[i, j + 1]) * quarter
        gv[1, s, j] = b[i, j] * half + (gr[i, j] + gr[i + 1, j]) * half + (b[i - 1, j] + b[i + 1, j]) * quarter


@kernel
def _gradients_row(m, i, gh, gv, r0, r1, b0, b1, d, s):
    """Step 2's gradients at plane row ``i`` into slot ``s`` of ``d`` (4, RING + 1, wq): |C(x) - C(x + 2)| of
    C = X - G along the rows at red (d[0]) and blue (d[2]) sites, along the columns (d[1], d[3]); ``r0``,
    ``r1`` the slots of rows i, i + 1 of the red planes of ``gh``, ``gv``; ``b0``, ``b1`` of the blue ones."""
    for k in range(2):
        x = m[3 * k]
        s0, s1 = (r0, r1) if k == 0 else (b0, b1)
        for j in range(1, m.shape[2] - 1):
            d[2 * k, s, j] = abs((x[i, j] - gh[k, s0, j]) - (x[i, j + 1] - gh[k, s0, j + 1]))
            d[2 * k + 1, s, j] = abs((x[i, j] - gv[k, s0, j]) - (x[i + 1, j] - gv[k, s1, j]))


@kernel(fastmath={"contract"})
def _decide_row(d, ru, rm, rd, bu, bm, bd, gh, gv, r0, b0, g, horizontal, s, sums):
    """Step 2's decision at one plane row: the window sums of the gradients ``d`` (module docstring; slots
    ``ru``, ``rm``, ``rd`` of the red planes' rows i - 1, i, i + 1, ``bu``, ``bm``, ``bd`` of the blue ones;
    summed in the order of OpenCV's filter2D over the full-resolution window); into slot ``s`` of ``g``
    (2, RING, wq) green along the rows (``gh``, slot ``r0`` red, ``b0`` blue) where the columns' sum is at
    least the rows', else along the columns (``gv``), ``horizontal`` 1 where along the rows."""
    three = np.float32(3.0)
    hr0, hr1, hr2, hb0, hb1, hb2 = d[0, ru], d[0, rm], d[0, rd], d[2, bu], d[2, bm], d[2, bd]
    vr0, vr1, vb0, vb1 = d[1, ru], d[1, rm], d[3, bu], d[3, bm]
    rows_r, cols_r, rows_b, cols_b = sums[0], sums[1], sums[2], sums[3]
    for j in range(1, d.shape[2] - 1):  # (the window sums first, a loop with few arrays: it vectorises)
        t = hr0[j - 1] + hr0[j] + hb0[j - 1]
        t = three * hr1[j] + (three * hr1[j - 1] + t)
        rows_r[j] = t + hb1[j - 1] + hr2[j - 1] + hr2[j]
        t = (three * vr0[j] + vr0[j - 1]) + vr0[j + 1] + vb0[j - 1] + vb0[j] + vr1[j - 1]
        cols_r[j] = three * vr1[j] + t + vr1[j + 1]
        t = hb0[j - 1] + hb0[j] + hr1[j]
        t = three * hb1[j] + (three * hb1[j - 1] + t)
        rows_b[j] = t + hr2[j] + hb2[j - 1] + hb2[j]
        t = (three * vb0[j] + vb0[j - 1]) + vb0[j + 1] + vr1[j] + vr1[j + 1] + vb1[j - 1]
        cols_b[j] = three * vb1[j] + t + vb1[j + 1]
    for k in range(2):
        _choose(sums[2 * k], sums[2 * k + 1], gh[k, r0 if k == 0 else b0], gv[k, r0 if k == 0 else b0],
                g[k, s], horizontal[k, s])


@kernel(inline="always")
def _choose(rows, cols, gh, gv, g, horizontal):
    """Green along the rows (``gh``; ``horizontal`` 1) where ``cols`` >= ``rows``, else ``gv``, into ``g``."""
    for j in range(1, g.size - 1):
        along = cols[j] >= rows[j]
        horizontal[j] = along
        g[j] = gh[j] if along else gv[j]


@kernel
def _at_green_row(m, i, g, r0, r1, bu, b0, out, s):
    """Step 3 at the green sites of plane row ``i``, into slot ``s`` of ``out`` (4, RING, wq): red and blue
    at the greens of red rows (out[0], out[1]) and of blue rows (out[2], out[3]): green plus the mean of
    X - G (``g``: green at the red sites, slots ``r0``, ``r1`` of rows i, i + 1, and at the blue ones, ``bu``,
    ``b0`` of rows i - 1, i) over the two X sites beside it."""
    half = np.float32(0.5)
    r, gr, gb, b, gre, gbl = m[0], m[1], m[2], m[3], g[0], g[1]
    for j in range(1, m.shape[2] - 1):
        out[0, s, j] = gr[i, j] + half * ((r[i, j] - gre[r0, j]) + (r[i, j + 1] - gre[r0, j + 1]))
        out[1, s, j] = gr[i, j] + half * ((b[i - 1, j] - gbl[bu, j]) + (b[i, j] - gbl[b0, j]))
        out[2, s, j] = gb[i, j] + half * ((r[i, j] - gre[r0, j]) + (r[i + 1, j] - gre[r1, j]))
        out[3, s, j] = gb[i, j] + half * ((b[i, j - 1] - gbl[b0, j - 1]) + (b[i, j] - gbl[b0, j]))


@kernel
def _at_opposite_row(m, i, greens, p0, p1, q0, qu, horizontal, h, before, c0, c1, centre, other):
    """Step 3 (``centre`` 0) and the refinement (1) at the red and blue sites of plane row ``i``: ``other``
    (2, wq), blue at the red sites and red at the blue ones: the site's value minus (plus) the mean of R - B
    over its two green neighbours along the chosen direction (``greens``: :func:`_at_green_row`'s ring; slots
    ``p0``, ``p1`` of rows i, i + 1 of the greens of red rows, ``q0``, ``qu`` of rows i, i - 1 of those of
    blue rows; ``horizontal`` slot ``h``) and, with weight ``centre``, the site's own R - B (``before``
    (2, ., wq), slots ``c0`` and ``c1``: its value from step 3; finite)."""
    r, b, rgr, bgr, rgb, bgb = m[0], m[3], greens[0], greens[1], greens[2], greens[3]
    scale = np.float32(2.0) + centre
    for j in range(1, m.shape[2] - 1):
        rows = (rgr[p0, j - 1] - bgr[p0, j - 1]) + (rgr[p0, j] - bgr[p0, j])
        cols = (rgb[qu, j] - bgb[qu, j]) + (rgb[q0, j] - bgb[q0, j])
        diff = (rows if horizontal[0, h, j] else cols) + centre * (r[i, j] - before[0, c0, j])
        other[0, j] = r[i, j] - diff / scale
        rows = (rgb[q0, j] - bgb[q0, j]) + (rgb[q0, j + 1] - bgb[q0, j + 1])
        cols = (rgr[p0, j] - bgr[p0, j]) + (rgr[p1, j] - bgr[p1, j])
        diff = (rows if horizontal[1, h, j] else cols) + centre * (before[1, c1, j] - b[i, j])
        other[1, j] = b[i, j] + diff / scale


@kernel
def _refine_row(m, i, greens, p0, p1, q0, qu, horizontal, h, g, g0, g1, out, s):
    """The refinement of green at the red and blue sites of plane row ``i`` into slot ``s`` of ``out``: the
    site's value minus the three-pixel mean of X - G along the chosen direction (``g``: green before, slots
    ``g0`` red, ``g1`` blue; other slots as :func:`_at_opposite_row`'s)."""
    third = np.float32(1.0 / 3.0)
    r, gr, gb, b, rgr, bgr, rgb, bgb = m[0], m[1], m[2], m[3], greens[0], greens[1], greens[2], greens[3]
    for j in range(1, m.shape[2] - 1):
        rows = (rgr[p0, j - 1] - gr[i, j - 1]) + (rgr[p0, j] - gr[i, j])
        cols = (rgb[qu, j] - gb[i - 1, j]) + (rgb[q0, j] - gb[i, j])
        out[0, s, j] = r[i, j] - third * ((rows if horizontal[0, h, j] else cols) + (r[i, j] - g[0, g0, j]))
        rows = (bgb[q0, j] - gb[i, j]) + (bgb[q0, j + 1] - gb[i, j + 1])
        cols = (bgr[p0, j] - gr[i, j]) + (bgr[p1, j] - gr[i + 1, j])
        out[1, s, j] = b[i, j] - third * ((rows if horizontal[1, h, j] else cols) + (b[i, j] - g[1, g1, j]))


@kernel
def _advance(m, rowsrc, rowin, colpad, colsrc, ncol, rings, hz, d, out, refine, lo, hi, t0, t1):
    """The demosaicing's stages (:data:`STAGES`; :data:`STAGES_UNREFINED` without ``refine``) from time
    ``t0`` to ``t1``: at time t stage k computes plane row t - k LAG where that is in its rows lo[k] to
    hi[k] (plane rows), columns 1 to wq - 2 of ``m`` (4, hq, wq; a whole frame's planes or a block of their
    columns), into its ring (``rings`` float32 (18, RING, wq): green along rows 0-1, along columns
    2-3, decided 4-5, red and blue at the greens 6-9, the opposite sites 10-11, refined green 12-13, red and
    blue at the greens again 14-17; ``hz`` uint8 (2, RING, wq) the decision; ``d`` (4, RING + 1, wq) the
    gradients, row RING zero). Rows of a plane outside the frame are read from their mirror sources
    (``rowsrc`` (2, hq) by row parity; ``rowin`` whether inside), padding columns mirrored after each row
    (``colpad``, ``colsrc`` (2, k) by column parity, ``ncol`` how many). The last stage's plane row r goes to
    ``out`` (n, 8, wq) row r % n: green at the red and blue sites, red and blue at the greens of red rows and of blue
    rows, blue at the red sites and red at the blue ones (:data:`OUTPUTS`)."""
    gh, gv, g0, gn0, o0, g1, gn1 = rings[0:2], rings[2:4], rings[4:6], rings[6:10], rings[10:12], rings[12:14], \
        rings[14:18]
    last = STAGES - 1 if refine else STAGES_UNREFINED - 1
    sums = np.empty((4, m.shape[2]), np.float32)
    other = np.empty((2, m.shape[2]), np.float32)
    n = out.shape[0]
    for t in range(t0, t1):
        for k in range(last + 1):
            r = t - k * LAG
            if r < lo[k] or r >= hi[k]:
                continue
            s = r % RING
            p0, p1 = _slot(rowsrc, 0, r), _slot(rowsrc, 0, r + 1)
            q0, q1, qu = _slot(rowsrc, 1, r), _slot(rowsrc, 1, r + 1), _slot(rowsrc, 1, r - 1)
            if k == 0:
                _green_row(m, r, gh, gv, s)
                for c in range(2):  # (plane 0 of each: red sites, column parity 0; plane 1: blue, 1)
                    _mirror_cols(gh[c, s], colpad[c], colsrc[c], ncol[c])
                    _mirror_cols(gv[c, s], colpad[c], colsrc[c], ncol[c])
            elif k == 1:
                _gradients_row(m, r, gh, gv, p0, p1, q0, q1, d, s)
                for c in range(4):
                    pads = colpad[c // 2]
                    for x in range(ncol[c // 2]):
                        d[c, s, pads[x]] = 0
            elif k == 2:
                _decide_row(d, _dslot(rowin, 0, r - 1), _dslot(rowin, 0, r), _dslot(rowin, 0, r + 1),
                            _dslot(rowin, 1, r - 1), _dslot(rowin, 1, r), _dslot(rowin, 1, r + 1),
                            gh, gv, p0, q0, g0, hz, s, sums)
                for c in range(2):
                    _mirror_cols(g0[c, s], colpad[c], colsrc[c], ncol[c])
            elif k == 3 or k == 6:
                g, gn = (g0, gn0) if k == 3 else (g1, gn1)
                _at_green_row(m, r, g, p0, p1, qu, q0, gn, s)
                for c in range(4):  # (greens of red rows: column parity 1; of blue rows: 0)
                    _mirror_cols(gn[c, s], colpad[1 - c // 2], colsrc[1 - c // 2], ncol[1 - c // 2])
            elif k == 4:
                _at_opposite_row(m, r, gn0, p0, p1, q0, qu, hz, r % RING, gv, p0, q0, np.float32(0.0), other)
                o0[:, s] = other
            elif k == 5:
                _refine_row(m, r, gn0, p0, p1, q0, qu, hz, s, g0, p0, q0, g1, s)
                for c in range(2):
                    _mirror_cols(g1[c, s], colpad[c], colsrc[c], ncol[c])
            else:
                _at_opposite_row(m, r, gn1, p0, p1, q0, qu, hz, r % RING, o0, s, s, np.float32(1.0), other)
            if k == last:
                g, gn = (g1, gn1) if refine else (g0, gn0)
                row = out[r % n]
                row[0], row[1] = g[0, p0], g[1, q0]
                row[2], row[3], row[4], row[5] = gn[0, p0], gn[1, p0], gn[2, q0], gn[3, q0]
                row[6], row[7] = other[0], other[1]


def _stage_rows(grid: Grid, first: int, last: int, stages: int) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) (stages,) intp: the plane rows each stage computes so that the last one gives rows ``first``
    to ``last``: each stage's rows' neighbours (r - 1 to r + 1) read through their mirror sources."""
    lo, hi = [0] * stages, [0] * stages
    lo[-1], hi[-1] = first, last
    for k in range(stages - 2, -1, -1):
        a, b = max(lo[k + 1] - 1, 0), min(hi[k + 1] + 1, grid.hq)
        # (a row's source is itself but in the padding, within LAG of the ends: the extremes are near a and b)
        near = set(range(a, min(a + LAG + 1, b))) | set(range(max(b - LAG - 1, a), b))
        ends = [grid.sources[p][r] for p in (0, 1) for r in near]
        lo[k], hi[k] = max(min(ends), 1), min(max(ends) + 1, grid.hq - 1)
    return np.array(lo, np.intp), np.array(hi, np.intp)


def _block_columns(grid: Grid, offset: int, width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The padding columns (colpad, colsrc, ncol as Grid's) of a block of the planes' columns ``offset`` to
    ``offset + width``, in its own columns: those inside it (where it reaches an edge of the frame)."""
    colpad, colsrc, ncol = np.zeros_like(grid.colpad), np.zeros_like(grid.colsrc), np.zeros_like(grid.ncol)
    if LAG < offset and offset + width < grid.wq - LAG:  # (the padding is within LAG columns of the ends)
        return colpad, colsrc, ncol
    for p in range(2):
        pads, sources = grid.colpad[p, :grid.ncol[p]] - offset, grid.colsrc[p, :grid.ncol[p]] - offset
        keep = (pads >= 0) & (pads < width) & (sources >= 0) & (sources < width)
        ncol[p] = keep.sum()
        colpad[p, :ncol[p]], colsrc[p, :ncol[p]] = pads[keep], sources[keep]
    return colpad, colsrc, ncol


def _scratch(width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The streamed stages' rings for planes ``width`` columns wide (:func:`_advance`'s ``rings``, ``d`` with its
    zero row, ``hz``)."""
    d = np.empty((4, RING + 1, width), np.float32)
    d[:, RING] = 0
    return np.empty((18, RING, width), np.float32), d, np.empty((2, RING, width), np.uint8)


def _stream(grid: Grid, m: np.ndarray, refine: bool, first: int, last: int, out: np.ndarray, chunk,
            columns: tuple[int, int] | None = None, rows: tuple[np.ndarray, np.ndarray] | None = None) -> None:
    """The demosaicing of plane rows ``first`` to ``last`` (of 1 .. hq - 2) of the planes ``m`` (float32, mirrored
    padding), in chunks of ``out``'s rows (n, 8, width): after each, ``chunk(a, b)`` with plane rows a to b in
    ``out`` rows a % n to (b - 1) % n (a run: chunks never wrap). ``columns``: (c0, c1), the plane columns
    computed, ``m`` then a block of the planes' columns c0 - 1 to c1 ((4, hq, width), width c1 - c0 + 2; its column
    j and ``out``'s the planes' c0 - 1 + j; at least rows lo - 1 to hi + 1 of :func:`_stage_rows` filled); by
    default 1 to wq - 1 of the whole planes (4, hq, wq). Columns within MARGIN of a c0 > 1 or a c1 < wq - 1 are
    not the whole frame's. ``rows``: :func:`_stage_rows`' (lo, hi) where the caller has them."""
    stages = STAGES if refine else STAGES_UNREFINED
    lo, hi = _stage_rows(grid, first, last, stages) if rows is None else rows
    colpad, colsrc, ncol = grid.colpad, grid.colsrc, grid.ncol
    if columns is not None:
        colpad, colsrc, ncol = _block_columns(grid, columns[0] - 1, m.shape[2])
    rings, d, hz = _scratch(m.shape[2])
    n = out.shape[0]
    t = int(min(lo[k] + k * LAG for k in range(stages)))
    a = first
    while a < last:
        b = min((a // n + 1) * n, last)
        end = b - 1 + (stages - 1) * LAG + 1
        _advance(m, grid.rowsrc, grid.rowin, colpad, colsrc, ncol, rings, hz, d, out, refine, lo, hi, t, end)
        t = end
        chunk(a, b)
        a = b


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
    out = np.empty((grid.hq, 8, grid.wq), np.float32)
    _stream(grid, m, refine, 1, grid.hq - 1, out, lambda a, b: None)
    full = np.empty((2 * grid.hq, 2 * grid.wq, 3), np.float32)
    for kind, (py, px) in enumerate(PARITY):
        full[py::2, px::2] = np.stack([m[kind] if k < 0 else out[:, k] for k in OUTPUTS[kind]], axis=-1)
    return full[grid.top:grid.top + grid.h, grid.left:grid.left + grid.w].copy()


@kernel(inline="always")
def _run(y, x0, top, left, w):
    """The pixels of frame row ``y`` at columns x0, x0 + 2, ... (one kind of site) in the quarter planes
    of a grid with padding ``top``, ``left``: (kind, plane row, first plane column, count)."""
    return 2 * ((y + top) % 2) + (x0 + left) % 2, (y + top) // 2, (x0 + left) // 2, (w - x0 + 1) // 2


@kernel(inline="always")  # (called from a kernel: inlined, its loops vectorise)
def _site_row(row, ex, cen, inverse_gain, floor_variance, floor, top, left, m, y, write, share, snr, level):
    """Row ``y`` of a rectangle of the frame: each pixel's share of its brightest channel of its own channel's value V
    (of ``row``, float32 (3 W,), its R, G, B; 1 where all are 0) into ``share`` (W,), V^2 / (V^2 + v) into ``snr`` (W,;
    v = (e V / g + floor variance) / e^2 the noise model's variance at its exposure e, of ``ex`` (W,); 0 where ``cen``
    (W,), a censored reading: its value is a fill, nothing measured there), and, if ``write``, max(V, 0) + ``floor``
    (through ``level``, (W,)) into the planes ``m`` (4, hq, wq) of the grid with padding ``top``, ``left``. (A flat row
    and selects between the channels, so that the loop vectorises.)"""
    zero, one = np.float32(0.0), np.float32(1.0)
    w = share.size
    red_row, odd_left = (y + top) % 2 == 0, left % 2
    for x in range(w):
        r, g, b = row[3 * x], row[3 * x + 1], row[3 * x + 2]
        odd = (x + odd_left) & 1 == 1
        v = (g if odd else r) if red_row else (b if odd else g)
        brightest = max(r, max(g, b))
        share[x] = v / brightest if brightest > zero else one
        positive = max(v, zero)
        e = ex[x]
        variance = (e * positive * inverse_gain + floor_variance) / (e * e)
        snr[x] = zero if cen[x] else positive * positive / (positive * positive + variance)
        level[x] = positive + floor
    if write:
        for x0 in range(2):
            kind, i, j0, n = _run(y, x0, top, left, w)
            plane = m[kind, i]
            for k in range(n):
                plane[j0 + k] = level[x0 + 2 * k]


@kernel(inline="always")
def _mirror(i, n):
    """Index ``i`` of 0 .. n - 1 mirrored about the edge with the edge repeated (-1 -> 0, n -> n - 1)."""
    return -1 - i if i < 0 else 2 * n - 1 - i if i >= n else i


@kernel(inline="always")
def _row_windows(share, snr, censored, smallest, total, near):
    """One row's horizontal parts of the weight's windows: the smallest share over x - 1 .. x + 1
    (``smallest``), the sum of ``snr`` over x - 2 .. x + 2 (``total``, mirrored about the edge with the edge
    repeated, as cv2.BORDER_REFLECT), whether x - 1 .. x + 1 holds a censored reading (``near``)."""
    w = share.size
    for x in range(1, w - 1):
        smallest[x] = min(share[x - 1], min(share[x], share[x + 1]))
    for x in range(1, w - 1):
        near[x] = censored[x - 1] | censored[x] | censored[x + 1]
    for x in range(2, w - 2):
        total[x] = snr[x - 2] + snr[x - 1] + snr[x] + snr[x + 1] + snr[x + 2]
    for x in (0, w - 1):
        lo, hi = max(x - 1, 0), min(x + 1, w - 1)
        smallest[x] = min(share[lo], min(share[x], share[hi]))
        near[x] = censored[lo] | censored[x] | censored[hi]
    for x in (0, 1, w - 2, w - 1):
        total[x] = (snr[_mirror(x - 2, w)] + snr[_mirror(x - 1, w)] + snr[x] + snr[_mirror(x + 1, w)]
                    + snr[_mirror(x + 2, w)])


@kernel(inline="always")
def _least(a, b, c, out):
    """Element-wise minimum of three rows."""
    for x in range(out.size):
        out[x] = min(a[x], min(b[x], c[x]))


@kernel(inline="always")
def _mean(a, b, c, d, e, scale, out):
    """The sum of five rows times ``scale``."""
    for x in range(out.size):
        out[x] = (a[x] + b[x] + c[x] + d[x] + e[x]) * scale


@kernel(inline="always")
def _any(a, b, c, out):
    """Element-wise or of three bool rows."""
    for x in range(out.size):
        out[x] = a[x] | b[x] | c[x]


@kernel(inline="always")
def _texture_row(level, across, left, texture, sums):
    """One row's colour texture (module docstring, Where) summed by tile into ``sums`` (k,): at each pixel but the
    row's ends, 2 |U - M| / (U + M), U its ``across`` (the cells' value of its neighbours' channel), M the mean
    of its two neighbours' ``level`` (their own readings' values), both plus the logarithm's floor. ``texture``
    (W,): scratch."""
    zero, two, half = np.float32(0.0), np.float32(2.0), np.float32(0.5)
    w = level.size
    texture[0], texture[w - 1] = zero, zero
    for x in range(1, w - 1):
        u, mid = across[x], half * (level[x - 1] + level[x + 1])
        texture[x] = two * abs(u - mid) / (u + mid)
    for t in range(sums.size):  # (tile t: frame columns 2 TILE t - left to 2 TILE (t + 1) - left)
        total = zero
        for x in range(max(2 * TILE * t - left, 0), min(2 * TILE * (t + 1) - left, w)):
            total += texture[x]
        sums[t] = total


@kernel
def _texture_rows(rgb, floor, top, left, activity, first, last):
    """Rows ``first`` to ``last`` of ``activity`` (H, k): each row's colour texture summed by tile
    (:func:`_texture_row`) of ``rgb`` (float32 (H, W, 3)), the pixels' own channels and their row neighbours'
    channels plus ``floor`` (grid padding ``top``, ``left``)."""
    zero = np.float32(0.0)
    w = rgb.shape[1]
    level, across, texture = np.empty(w, np.float32), np.empty(w, np.float32), np.empty(w, np.float32)
    for y in range(first, last):
        row, red_row, odd_left = rgb[y].reshape(-1), (y + top) % 2 == 0, left % 2
        for x in range(w):
            r, g, b = row[3 * x], row[3 * x + 1], row[3 * x + 2]
            odd = (x + odd_left) & 1 == 1
            v = (g if odd else r) if red_row else (b if odd else g)
            u = (r if odd else g) if red_row else (g if odd else b)
            level[x] = max(v, zero) + floor
            across[x] = max(u, zero) + floor
        _texture_row(level, across, left, texture, activity[y])


@kernel(inline="always")
def _clipped_row(censored, y, x0, top, left, out):
    """The clipped readings of frame row ``y``, columns x0 to x0 + n, into ``out`` (n,): censored (``censored``, bool
    (H, W)) with no uncensored reading of their own channel in their 5x5, the channel clipped there (a censored long
    reading beside uncensored short ones of its channel holds a value, the fill, not a bound). ``top``, ``left``:
    the parities of the grid's padding at (y, x0)."""
    h, w = censored.shape
    green_parity = (top + 1) % 2  # (k + left) % 2 of the greens in this row
    for k in range(out.size):
        x = x0 + k
        clipped = censored[y, x]
        if clipped:
            green = (k + left) % 2 == green_parity
            for dy in range(-2, 3):
                for dx in range(-2, 3):
                    yy, xx = y + dy, x + dx
                    same = (dy % 2 == 0 and dx % 2 == 0) or (green and abs(dy) == 1 and abs(dx) == 1)
                    if same and 0 <= yy < h and 0 <= xx < w and not censored[yy, xx]:
                        clipped = False
        out[k] = clipped


@kernel
def _site_weights_rows(rgb, exposure, censored, y0, x0, inverse_gain, floor_variance, floor, low, scale, top, left,
                       m, weight, first, last):
    """Rows ``first`` to ``last`` of the weight (module docstring, Where; float32 (h, w)) of the rectangle of the
    frame at (``y0``, ``x0``) (``rgb``, ``exposure``, ``censored``: the frame's; ``top``, ``left``: the padding of
    the grid of ``m`` about the rectangle), its windows inside the rectangle, in one pass over
    rings of five rows: the lattice blend of the 3x3's smallest share times the 5x5 mean of the sites'
    signal-to-noise weights, 0 within a pixel of a clipped reading (:func:`_clipped_row` of ``censored``, bool
    (H, W)). The planes ``m`` get those rows' max(V, 0) + ``floor`` (:func:`_site_row`). Returns the count of
    nonzero weights."""
    h, w = weight.shape
    zero, one, fifth = np.float32(0.0), np.float32(1.0), np.float32(1.0 / 25.0)
    share, snr, level = np.empty(w, np.float32), np.empty(w, np.float32), np.empty(w, np.float32)
    clipped = np.empty(w, np.bool_)
    smallest, total = np.empty((5, w), np.float32), np.empty((5, w), np.float32)
    near = np.empty((5, w), np.bool_)
    least, mean, close = np.empty(w, np.float32), np.empty(w, np.float32), np.empty(w, np.bool_)
    done = max(first - 2, 0)  # the next row to compute
    count = 0
    for y in range(first, last):
        while done <= min(y + 2, h - 1):
            _site_row(rgb[y0 + done].reshape(-1)[3 * x0:3 * (x0 + w)], exposure[y0 + done, x0:x0 + w],
                      censored[y0 + done, x0:x0 + w], inverse_gain, floor_variance, floor, top, left, m, done,
                      first <= done < last, share, snr, level)
            _clipped_row(censored, y0 + done, x0, (done + top) % 2, left % 2, clipped)
            _row_windows(share, snr, clipped, smallest[done % 5], total[done % 5], near[done % 5])
            done += 1
        up, down = max(y - 1, 0) % 5, min(y + 1, h - 1) % 5
        # (the columns' parts one after the other: few arrays a loop, so that each vectorises)
        _least(smallest[up], smallest[y % 5], smallest[down], least)
        _mean(total[_mirror(y - 2, h) % 5], total[_mirror(y - 1, h) % 5], total[y % 5],
              total[_mirror(y + 1, h) % 5], total[_mirror(y + 2, h) % 5], fifth, mean)
        _any(near[up], near[y % 5], near[down], close)
        out = weight[y]
        for x in range(w):
            wt = min(max((least[x] - low) * scale, zero), one) * mean[x]
            wt = zero if close[x] else wt
            out[x] = wt
            count += wt > zero
    return count


@kernel
def _blend(rgb, luminance, weight, wy, wx, exps, offset, floor, share, top, left, first, last, x0, x1):
    """Frame rows ``first`` to ``last``, columns ``x0`` to ``x1``: at each pixel of nonzero ``weight`` (its frame pixel
    (y, x) at (y - ``wy``, x - ``wx``)), its other two channels move by the weight towards exp of their demosaiced
    logarithms minus ``floor`` (at least 0; ``exps``: (n, 8, wq), plane row i of :func:`_advance`'s output exponentiated
    at row i % n, its column j the planes' j + ``offset``), and the luminance becomes sum_c n_c RGB_c (``share``)."""
    zero = np.float32(0.0)
    w = luminance.shape[1]
    n = exps.shape[0]
    first_other, second_other = np.empty(w, np.float32), np.empty(w, np.float32)
    n0, n1, n2 = share[0], share[1], share[2]
    for y in range(first, last):
        red_row, odd_left = (y + top) % 2 == 0, left % 2
        for xs in range(2):  # each pixel's other channels (R before G before B) into rows of the frame
            kind, i, j0, count = _run(y, xs, top, left, w)
            e = exps[i % n]
            a, b = (e[0], e[6]) if kind == R else (e[7], e[1]) if kind == B else \
                (e[2], e[3]) if kind == GR else (e[4], e[5])
            for k in range(max((x0 - xs + 1) // 2, 0), min((x1 - xs + 1) // 2, count)):
                first_other[xs + 2 * k] = max(a[j0 + k - offset] - floor, zero)
                second_other[xs + 2 * k] = max(b[j0 + k - offset] - floor, zero)
        # (rows sliced to the columns, C-contiguous: the loop from 0 vectorises)
        _blend_row(rgb[y].reshape(-1)[3 * x0:3 * x1], luminance[y, x0:x1], weight[y - wy, x0 - wx:x1 - wx],
                   first_other[x0:x1], second_other[x0:x1], red_row, (odd_left + x0) % 2, n0, n1, n2)


@kernel(inline="always")
def _blend_row(row, lum, weight, first_other, second_other, red_row, odd_left, n0, n1, n2):
    """One row of :func:`_blend` (``row``: the flat RGB row; selects, so that it vectorises)."""
    zero = np.float32(0.0)
    for x in range(lum.size):
        wt = weight[x]
        r, g, b = row[3 * x], row[3 * x + 1], row[3 * x + 2]
        odd = (x + odd_left) & 1 == 1
        red, blue = red_row and not odd, odd and not red_row
        new_r = r if red else r + wt * (first_other[x] - r)
        green_target = first_other[x] if red else second_other[x]
        new_g = g if not (red or blue) else g + wt * (green_target - g)
        new_b = b if blue else b + wt * (second_other[x] - b)
        moved = wt > zero
        row[3 * x] = new_r if moved else r
        row[3 * x + 1] = new_g if moved else g
        row[3 * x + 2] = new_b if moved else b
        lum[x] = n0 * new_r + n1 * new_g + n2 * new_b if moved else lum[x]


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
                         floor: float, refine: bool = True, workers: int | Executor = 1,
                         texture: float | None = TEXTURE) -> bool:
    """The stage (module docstring) into ``rgb`` (float32 (H, W, 3), linear, DN at exposure 1) and
    ``luminance`` (float32 (H, W), Y), in place. ``share``: n_c of the CFA. ``floor``: the logarithm's
    floor (DN at exposure 1; the longest exposure's read-noise floor). Each pixel keeps its own channel.
    ``texture``: the tiles' least mean colour texture (module docstring, Where; None: every tile).
    ``workers``: threads for its pieces (base.map_on); the result does not depend on it.
    Returns False (nothing done) where it does not apply (not a 2x2 Bayer CFA, a frame under 5x5)."""
    h, w = luminance.shape
    red = red_site(inp)
    if red is None or h < 5 or w < 5 or inp.channels is None:
        return False
    f32 = np.float32
    grid = Grid((h, w), red)
    activity = np.empty((h, (grid.left + w) // 2 // TILE + 1), f32)
    map_on(workers, lambda part: _texture_rows(rgb, f32(floor), grid.top, grid.left, activity, part.start, part.stop),
           _pieces(h))
    n, exposure = np.asarray(share, f32), np.asarray(inp.exposure, f32)
    stages = STAGES if refine else STAGES_UNREFINED

    def columns(item: tuple[int, int, int, int]) -> tuple[int, int]:  # computed: MARGIN more, to an edge near one
        c0, c1 = max(item[2] - MARGIN, 1), min(item[3] + MARGIN, grid.wq - 1)
        return 1 if c0 <= MARGIN else c0, grid.wq - 1 if c1 >= grid.wq - 1 - MARGIN else c1

    def prepare(items: list[tuple[int, int, int, int]]) -> list:
        out = []
        for item in items:
            lo, hi = _stage_rows(grid, item[0], item[1], stages)
            rows = (max(int(lo.min()) - 1, 0), min(int(hi.max()) + 1, grid.hq))
            out.append((_block(inp, rgb, exposure, grid, f32(floor), rows, columns(item)), (lo, hi)))
        return out

    def run(pieces: list) -> None:
        for (first, last, j0, j1), ((m, weight, (y0, x0)), stage_rows) in pieces:
            c0, c1 = columns((first, last, j0, j1))
            ya, yb = max(2 * first - grid.top, 0), min(2 * last - grid.top, h)  # (the frame's pixels of the tiles)
            xa, xb = max(2 * j0 - grid.left, 0), min(2 * j1 - grid.left, w)
            if not weight[ya - y0:yb - y0, xa - x0:xb - x0].any():
                continue
            exps = np.empty((CHUNK, 8, m.shape[2]), f32)

            def chunk(a: int, b: int) -> None:  # plane rows a to b: exp, then the frame rows they hold
                part = exps[a % CHUNK:(b - 1) % CHUNK + 1].reshape(-1, m.shape[2])
                cv2.exp(part, part)
                _blend(rgb, luminance, weight, y0, x0, exps, c0 - 1, f32(floor), n, grid.top, grid.left,
                       max(2 * a - grid.top, 0), min(2 * b - grid.top, h), xa, xb)

            _stream(grid, m, refine, first, last, exps, chunk, (c0, c1), stage_rows)

    items = _spans(grid, activity, texture)
    count = 1 if workers == 1 else min(len(items), 4)
    groups = [items[k::count] for k in range(count)]
    # every block read before any pixel changes (a block's margins are other tiles' pixels)
    blocks = map_on(workers, prepare, groups)
    map_on(workers, run, [list(zip(group, made)) for group, made in zip(groups, blocks)])
    return True


def _block(inp: SveInput, rgb: np.ndarray, exposure: np.ndarray, grid: Grid, floor: np.float32,
           rows: tuple[int, int], columns: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """A block of the demosaicing's input and the weight (module docstring, Where) about it: ``m`` (4, hq, width)
    float32, width c1 - c0 + 2, plane rows ``rows`` (r0, r1) and columns c0 - 1 to c1 (``columns`` (c0, c1)) of the
    planes of ln(max(V, 0) + ``floor``) (``exposure``: float32 (H, W), the readings') with mirrored padding (other rows
    not filled); the weight of the frame's pixels of those rows and columns (float32 (Y1 - Y0, X1 - X0)) and its corner
    (Y0, X0). The weight's windows read only that rectangle: within 3 pixels of an edge of it that is not the frame's,
    it is not the frame's."""
    f32 = np.float32
    (r0, r1), (c0, c1) = rows, columns
    offset, width = c0 - 1, c1 - c0 + 2
    y0, y1 = max(2 * r0 - grid.top, 0), min(2 * r1 - grid.top, grid.h)
    x0, x1 = max(2 * offset - grid.left, 0), min(2 * (offset + width) - grid.left, grid.w)
    m = np.empty((4, grid.hq, width), f32)
    weight = np.empty((y1 - y0, x1 - x0), f32)
    sensor = inp.sensor
    _site_weights_rows(rgb, exposure, inp.censored, y0, x0, f32(1.0 / sensor.effective_gain),
                       f32(sensor.floor_variance), floor, f32(F_LOW), f32(1.0 / (F_HIGH - F_LOW)),
                       grid.top + y0, grid.left + x0 - 2 * offset, m, weight, 0, y1 - y0)
    colpad, colsrc, ncol = _block_columns(grid, offset, width)
    for kind, (py, px) in enumerate(PARITY):
        plane = m[kind]
        pads, sources = grid._rows[py]
        keep = (pads >= r0) & (pads < r1)
        plane[pads[keep]] = plane[sources[keep]]
        plane[r0:r1, colpad[px, :ncol[px]]] = plane[r0:r1, colsrc[px, :ncol[px]]]
        cv2.log(plane[r0:r1], plane[r0:r1])
    return m, weight, (y0, x0)


def _spans(grid: Grid, activity: np.ndarray, texture: float | None) -> list[tuple[int, int, int, int]]:
    """The pieces of the demosaicing: (first, last, j0, j1), plane rows of one chunk (CHUNK rows) and plane columns
    of a run of its tiles (TILE columns) whose mean colour texture (``activity``, (H, k) :func:`_texture_row`'s
    sums) is above ``texture`` (None: every tile), runs less than two margins apart merged, and a run with the same
    columns as one in the chunk above joined to it."""
    h, w = grid.h, grid.w
    band = (np.arange(h) + grid.top) // 2 // CHUNK
    starts = np.flatnonzero(np.r_[True, band[1:] != band[:-1]])
    tile = (np.arange(w) + grid.left) // 2 // TILE
    sums = np.add.reduceat(activity, starts, axis=0)
    counts = np.diff(np.r_[starts, h])[:, None] * np.bincount(tile, minlength=activity.shape[1])[None, :]
    active = np.ones(sums.shape, bool) if texture is None else sums > texture * np.maximum(counts, 1)
    items: list[tuple[int, int, int, int]] = []
    above: dict[tuple[int, int], int] = {}  # the chunk above's runs: their item
    for b, row in zip(band[starts], active):
        first, last = max(b * CHUNK, 1), min((b + 1) * CHUNK, grid.hq - 1)
        edges = np.flatnonzero(np.diff(np.r_[False, row, False]))
        runs = list(zip(edges[::2], edges[1::2]))
        merged: list[list[int]] = []
        for t0, t1 in runs:
            if merged and (t0 - merged[-1][1]) * TILE < 2 * MARGIN:
                merged[-1][1] = t1
            else:
                merged.append([t0, t1])
        here = {}
        for t0, t1 in merged:
            span = (max(t0 * TILE, 1), min(t1 * TILE, grid.wq - 1))
            k = above.get(span, -1)
            if k >= 0:  # (the same columns as the chunk above: one stream, its rows not computed twice)
                items[k] = (items[k][0], last, *span)
            else:
                k = len(items)
                items.append((first, last, *span))
            here[span] = k
        above = here
    return items
