"""The chroma at cell resolution (svelive.reconstruction.colour, step a): each channel's cell values
smoothed over 3x3 cells and moved to the cells' centres, the shares k_c = C_c / L and the coarse
luminance, the blend towards each cell's own shares and the garrote towards the neutral, the median over
3x3 cells and the normalisation (:func:`chroma`)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from svelive.jit import fma32, kernel
from svelive.reconstruction.colour.cells import CellLayout, _cell_stats_row, cell_layout
from svelive.reconstruction.colour.highlights import _cell_values_row, white_balance
from svelive.reconstruction.methods.base import SveInput, binomial_kernel

#: A channel's share of luminance is at least this (a zero would make its pixels' exposure 0).
SHARE_FLOOR = 1e-3
#: Variance standing for "no coarse luminance here" (finite, so that interpolating it stays large).
COARSE_NONE = 1e30
#: Cell rows of each scratch plane of :func:`_share_pass` (rings: a stage reads rows at most 5 behind the
#: newest written).
PASS_ROWS = 8
#: Cell rows of each ring of the cells' statistics, smoothing and censoring in :func:`_chroma_pass` (at least 4: the
#: pass reads rows up to 3 behind the newest).
CELL_ROWS = 4
#: Cell rows around a cell row that its chroma reads (:func:`partial_chroma`): the smoothing, the centring, the two
#: 3x3 means and the median read one more each.
CHROMA_HALO = 5


@dataclass(frozen=True)
class Chroma:
    """A colour frame's chroma at cell resolution.

    Attributes:
        shares: float32 (3, Hc, Wc), k_c = C_c / L at each cell's centre, at least SHARE_FLOOR;
            a neutral surface's shares where L is 0.
        coarse: float32 (2, Hc, Wc), the luminance L = sum_c n_c C_c at each cell's centre and
            its noise variance (DN, DN^2); the variance is COARSE_NONE within 3x3 cells of a
            censored reading (the censoring rules bias L there, and Y's variance means less).
        layout: the cells' layout.
        white: float32 (3,), the white balance: camera RGB of a neutral surface, G = 1.
        shape: (H, W) of the frame.
    """

    shares: np.ndarray
    coarse: np.ndarray
    layout: CellLayout
    white: np.ndarray
    shape: tuple[int, int]

    @property
    def planes(self) -> np.ndarray | None:
        """float32 (5, Hc, Wc), the one array whose views ``shares`` and ``coarse`` are (:func:`chroma`'s,
        :func:`partial_chroma`'s, :meth:`fused`'s), or None where they are arrays of their own."""
        base = self.shares.base
        if (base is None or base is not self.coarse.base or base.shape != (5, *self.shares.shape[1:])
                or self.shares.ctypes.data != base.ctypes.data or self.coarse.ctypes.data != base[3].ctypes.data):
            return None
        return base

    def fused(self, planes: np.ndarray) -> Chroma:
        """The same chroma with a stream's fused shares and coarse luminance, (5, Hc, Wc) planes."""
        return Chroma(planes[:3], planes[3:5], self.layout, self.white, self.shape)


def chroma(inp: SveInput, white: np.ndarray | None = None) -> Chroma:
    """The chroma of a colour frame (package docstring, step a), at cell resolution; ``white`` (float32 (3,)):
    the white balance to take instead of this frame's (:func:`partial_chroma`).

    Each channel's cell means are smoothed over 3x3 cells ([1, 2, 1] / 4 each way, weighted by
    the share of each cell's information its uncensored readings hold, the smallest over the
    channels: :func:`_smooth_step`), the censoring and
    highlight rules give C_c, which is moved from the centroid of the channel's samples to the
    cells' centres (bilinearly), and the shares are k_c = C_c / L there. The same from each
    cell's own readings moves them where the two differ beyond noise (:func:`_blend_row`), the
    garrote towards the neutral follows (:func:`_shrink_row`), then each channel's median over 3x3
    cells (a cell straddling an edge is an outlier) and the scaling to sum_c n_c k_c = 1: all of
    it after the white balance in one pass over the cell rows (:func:`_share_pass`). With ``white`` given, the
    cells' statistics and smoothing are made in that pass too (:func:`_chroma_pass`), the same values without
    their planes of the whole frame (which the white balance reads otherwise).
    """
    layout = cell_layout(inp.pattern, inp.cfa)
    (cy, cx), (h, w) = layout.cell, inp.shape
    hc, wc = -(-h // cy), -(-w // cx)
    f32 = np.float32
    sensor = inp.sensor
    per_pixel = inp.pattern.pixel_map is not None
    stats = (inp.signal / inp.exposure if per_pixel else inp.signal, inp.censored, layout.channels, layout.levels,
             layout.exposures, per_pixel, f32(1.0 / sensor.effective_gain), f32(sensor.floor_variance),
             f32(sensor.censor_level))
    stats_scratch = np.empty((3, 3, layout.exposures.size, wc), f32), np.empty((6, wc), f32)
    k = binomial_kernel(3)
    spread = f32(np.sum(k * k) ** 2)  # the sum of the squared weights of the cells' smoothing
    smooth_scratch = np.empty((4, 3, wc), f32), np.empty(wc, f32)
    planes = np.empty((5, hc, wc), f32)  # (one array: a stream fuses it in place, Chroma.planes)
    shares, coarse = planes[:3], planes[3:]
    pass_scratch = (*(np.empty((3, PASS_ROWS, wc), f32) for _ in range(8)), coarse, shares,
                    np.empty((4, 3, 3, wc), f32), np.empty((3, wc), f32), np.empty(wc, f32))
    rows = hc if white is None else CELL_ROWS  # (whole planes, or rings of the last CELL_ROWS cell rows)
    mean, info, kept, weighted, bound, numerator, denominator = (np.empty((3, rows, wc), f32) for _ in range(7))
    flags = np.empty((2, rows, wc), np.uint8)
    if white is not None:  # a stream's partial chroma: the statistics and the smoothing in the share pass's rows
        white = np.asarray(white, f32)
        neutral = (white / f32(layout.share @ white)).astype(f32)
        _chroma_pass(*stats, mean, info, kept, weighted, bound, flags, *stats_scratch, k, numerator, denominator,
                     *smooth_scratch, np.empty((rows, wc), np.uint8), np.empty(wc, np.uint8), white, layout.share,
                     neutral, f32(SHARE_FLOOR), spread, _centring_taps(layout), *pass_scratch)
        return Chroma(shares, coarse, layout, white, (h, w))
    _cell_pass(*stats, mean, info, kept, weighted, bound, flags, *stats_scratch, k, numerator, denominator,
               *smooth_scratch)
    box = np.ones((3, 3), np.uint8)  # within 3x3 cells of: a channel with only censored readings, any censored
    clipped, censored = (cv2.dilate(flags[k], box, borderType=cv2.BORDER_REFLECT_101) for k in range(2))
    white = white_balance(numerator, denominator, info, clipped, layout.share, spread)
    # the rest in one pass over the cell rows (:func:`_share_pass`): every stage's rows are still in cache when
    # the next reads them, instead of a dozen passes over whole (3, Hc, Wc) planes
    neutral = (white / f32(layout.share @ white)).astype(f32)
    _share_pass(numerator, denominator, weighted, kept, mean, info, bound, censored, white, layout.share, neutral,
                f32(SHARE_FLOOR), spread, _centring_taps(layout), k, *pass_scratch)
    return Chroma(shares, coarse, layout, white, (h, w))


def partial_chroma(inp: SveInput, runs: list[tuple[int, int]], history: np.ndarray, white: np.ndarray) -> Chroma:
    """A colour frame's chroma on some cell rows only, a stream's ``history`` elsewhere (the band refresh of a
    still view, svelive.reconstruction.settle): :func:`chroma` with the white balance ``white`` (float32 (3,)) on
    the cell rows of ``runs`` ([start, stop) cell rows, apart), each run made from a crop of the frame with
    CHROMA_HALO cell rows around it (which its passes read; the same values as the whole frame's chroma with that
    white); the shares and coarse luminance of the other cell rows are ``history``'s (float32 (5, Hc, Wc), a
    stream's fused chroma: svelive.reconstruction.stream.fuse_chroma), in one new array (:attr:`Chroma.planes`)."""
    layout = cell_layout(inp.pattern, inp.cfa)
    cy, h = layout.cell[0], inp.shape[0]
    hc = history.shape[1]
    planes = np.empty_like(history)
    kept = 0  # (only the cell rows kept are copied: the runs' are written below)
    for a, b in [*runs, (hc, hc)]:
        planes[:, kept:a] = history[:, kept:a]
        kept = b
    for a, b in runs:
        lo, hi = max(a - CHROMA_HALO, 0), min(b + CHROMA_HALO, hc)
        part = chroma(inp.crop(slice(lo * cy, min(hi * cy, h))), white)
        planes[:3, a:b] = part.shares[:, a - lo:b - lo]
        planes[3:5, a:b] = part.coarse[:, a - lo:b - lo]
    return Chroma(planes[:3], planes[3:5], layout, np.asarray(white, np.float32), (h, inp.shape[1]))


@kernel
def _cell_pass(pixels, lost, channels, levels, exposures, per_pixel, gain_inv, floor_variance, censor, mean, info,
               kept, weighted, bound, flags, sums, scratch, k, numerator, denominator, rings, row):
    """svelive.reconstruction.colour.cells._cell_stats and the cells' smoothing (:func:`_smooth_step`; their
    arguments in turn) in one pass over the cell rows: each cell row's statistics smoothed along the row while they
    are in cache, into whole planes (which the white balance reads)."""
    hc = mean.shape[1]
    for t in range(hc + 1):
        if t < hc:
            _cell_stats_row(pixels, lost, channels, levels, exposures, per_pixel, gain_inv, floor_variance, censor,
                            mean, info, kept, weighted, bound, flags, sums, scratch, t, t)
        _smooth_step(weighted, kept, mean, k, numerator, denominator, rings, row, t, hc)


@kernel
def _smooth_step(weighted, kept, mean, k, numerator, denominator, rings, row, t, hc):
    """Step ``t`` of the cells' 3x3 smoothing over ``hc`` cell rows (the sums (3, Hc, Wc)): cell row ``t`` along
    the row, cell row t - 1 across, one row behind; the cells' planes are whole (``hc`` rows) or rings of their
    last rows (cell row i at i % rows). Every channel of a cell is weighted alike, by the smallest share of a
    channel's information its uncensored readings hold in it.

    Per channel (``kept`` of each) a cell beside a light that clipped some channels gave its
    unclipped channels in full and its clipped ones at the share of their unclipped (darker)
    readings: on dual-ISO a 3x3 orange light whose red and green clip the long rows spread its
    blue, measured there, into the dark cells around, whose shares turned violet (blue 5.5 times
    the luminance) and the 3x3 median carried that into the light. With one weight for every
    channel the ratios the smoothing forms are those of the cells it averages. Where that weight is
    0 for every cell around (a channel with only censored readings in each), each channel keeps
    the cell's own readings (the highlight rules take the censored ones).

    ``numerator`` (out): the smoothing ``k`` (float32 (3,), symmetric) each way, mirrored at the
    edges, of the common weight times ``mean``; ``denominator`` (out): of the common weight (the
    same in each channel's plane), bit for bit OpenCV's ``sepFilter2D``. ``rings`` (4, 3, Wc): the
    last three rows of the pass along rows (numerators, then the weight); ``row`` (Wc,): scratch.
    """
    m, wc = kept.shape[1], kept.shape[2]
    if t < hc:
        ti = t % m
        common = rings[3, t % 3]  # the weight's row first, smoothed along the row below
        for j in range(wc):
            row[j] = min(min(kept[0, ti, j], kept[1, ti, j]), kept[2, ti, j])
        for c in range(3):
            products, mc = common, mean[c, ti]  # (a scratch row: the ring's slot is written after it)
            for j in range(wc):
                products[j] = row[j] * mc[j]
            _binomial_along(products, k, rings[c, t % 3])
        _binomial_along(row, k, common)
    u = t - 1
    if 0 <= u < hc:
        up, down, ui = _mirrored(u - 1, hc), _mirrored(u + 1, hc), u % m
        for c in range(4):
            _binomial_across(rings[c, up % 3], rings[c, u % 3], rings[c, down % 3], k,
                             numerator[c, ui] if c < 3 else denominator[0, ui])
        d0, d1, d2 = denominator[0, ui], denominator[1, ui], denominator[2, ui]
        for j in range(wc):  # (numba's slice assignment copies one element a step: 5 times this loop's time)
            d1[j] = d0[j]
            d2[j] = d0[j]
        for j in range(wc):
            if d0[j] <= 0:  # no weight around: each channel's own readings
                for c in range(3):
                    numerator[c, ui, j], denominator[c, ui, j] = weighted[c, ui, j], kept[c, ui, j]


@lru_cache(maxsize=16)
def _centring_kernels(layout: CellLayout) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """Per channel, the (rows, cols) 3-tap kernels of the bilinear shift that moves its values from
    the centroid of its samples to the cells' centres: cell i reads i + d, d = (centre - origin) /
    cell (|d| < 1), float32, read-only."""
    out = []
    for c in range(3):
        pair = []
        for axis in range(2):
            d = (layout.centre[axis] - layout.origin[c, axis]) / layout.cell[axis]
            kernel = np.zeros(3, np.float32)  # taps at offsets -1, 0, +1
            kernel[1], kernel[2 if d >= 0 else 0] = 1 - abs(d), abs(d)
            kernel.setflags(write=False)
            pair.append(kernel)
        out.append(tuple(pair))
    return tuple(out)


@lru_cache(maxsize=16)
def _centring_taps(layout: CellLayout) -> np.ndarray:
    """:func:`_centring_kernels` as one float32 (3, 2, 3) array: per channel the taps along rows (0) and
    along columns (1), read-only."""
    taps = np.array([[rows, cols] for rows, cols in _centring_kernels(layout)], np.float32)
    taps.setflags(write=False)
    return taps


@kernel
def _share_pass(numerator, denominator, weighted, kept, mean, info, bound, censored, white, share, neutral, floor,
                spread, taps, k, values, own, smoothed, own_shares, noise, own_noise, residual, deviation, coarse,
                out, rings, columns, lum):
    """Step (a) after the cells' smoothing and the white balance, in one pass over the cell rows: each
    row's values (:func:`_cell_values_row`, smoothed and own), moved to the cells' centres (``taps``,
    :func:`_centring_taps`), their shares and coarse luminance (:func:`_shares_row`,
    :func:`_own_shares_row`), the 3x3 mean of the squared own - smoothed residual, the blend towards
    the own shares (:func:`_blend_row`), the 3x3 mean of the squared deviation from the neutral, the
    garrote towards it (:func:`_shrink_row`), the 3x3 median and the normalisation
    (:func:`_normalise_row`). Bit for bit the chain of whole-plane steps with OpenCV's filters it
    replaces (``sepFilter2D`` with the binomial ``k`` and its mirrored border, with the centring
    taps and the edge's value repeated, ``medianBlur`` of 3): each stage runs on a row a few rows
    behind the one before, whose rows it reads are then done and still in cache.

    In: the cells' statistics and sums (3, Hc, Wc) (:func:`chroma`), ``censored`` uint8 (Hc, Wc),
    ``white``, ``share``, ``neutral`` float32 (3,), ``floor`` and ``spread`` float32, ``taps``
    float32 (3, 2, 3), ``k`` float32 (3,). Out: ``out`` (3, Hc, Wc), the shares; ``coarse`` (2, Hc,
    Wc) (:func:`_shares_row`). Scratch: ``values``, ``own``, ``smoothed``, ``own_shares``,
    ``noise``, ``own_noise``, ``residual``, ``deviation`` (3, R, Wc), rings of the last R cell rows (cell
    row u at u % R; R at least 6, :data:`PASS_ROWS`: whole planes of them were 28 MB written and read again at
    1920x1200, 40 % of the pass); ``rings`` (4, 3, 3, Wc), the last three rows of each filter's pass along
    rows; ``columns`` (3, Wc) (:func:`_median_row`); ``lum`` (Wc,).
    """
    for t in range(out.shape[1] + 4):
        _share_step(numerator, denominator, weighted, kept, mean, info, bound, censored, white, share, neutral, floor,
                    spread, taps, k, values, own, smoothed, own_shares, noise, own_noise, residual, deviation, coarse,
                    out, rings, columns, lum, t)


@kernel
def _share_step(numerator, denominator, weighted, kept, mean, info, bound, censored, white, share, neutral, floor,
                spread, taps, k, values, own, smoothed, own_shares, noise, own_noise, residual, deviation, coarse,
                out, rings, columns, lum, t):
    """Step ``t`` of :func:`_share_pass` (its stages on cell rows t to t - 4); the cells' statistics, sums and
    ``censored`` are whole planes or rings of their last rows (cell row i at i % rows: :func:`_chroma_pass`)."""
    hc, n, m = out.shape[1], values.shape[1], mean.shape[1]
    if t < hc:  # the cells' values of row t, and the centring along the row
        r = t % n
        _cell_values_row(numerator, denominator, mean, info, bound, white, values, t % m, r)
        _cell_values_row(weighted, kept, mean, info, bound, white, own, t % m, r)
        for c in range(3):
            _taps_along(values[c, r], taps[c, 1], rings[0, t % 3, c])
            _taps_along(own[c, r], taps[c, 1], rings[1, t % 3, c])
    u = t - 1
    if 0 <= u < hc:  # centred, the shares of row u, and its residual along the row
        up, down, r = max(u - 1, 0), min(u + 1, hc - 1), u % n
        for c in range(3):
            _taps_across(rings[0, up % 3, c], rings[0, u % 3, c], rings[0, down % 3, c], taps[c, 0],
                         smoothed[c, r])
            _taps_across(rings[1, up % 3, c], rings[1, u % 3, c], rings[1, down % 3, c], taps[c, 0],
                         own_shares[c, r])
        _shares_row(smoothed, info, bound, censored, share, neutral, floor, spread, coarse, noise, u, u % m, r)
        _own_shares_row(own_shares, info, share, neutral, floor, smoothed, own_noise, residual, lum, u % m, r)
        for c in range(3):
            _binomial_along(residual[c, r], k, rings[2, u % 3, c])
    u = t - 2
    if 0 <= u < hc:  # the residual's 3x3 mean, the blend, and the deviation along the row
        up, down, r = _mirrored(u - 1, hc), _mirrored(u + 1, hc), u % n
        for c in range(3):
            _binomial_across(rings[2, up % 3, c], rings[2, u % 3, c], rings[2, down % 3, c], k, residual[c, r])
        _blend_row(smoothed, noise, own_shares, own_noise, residual, neutral, deviation, r)
        for c in range(3):
            _binomial_along(deviation[c, r], k, rings[3, u % 3, c])
    u = t - 3
    if 0 <= u < hc:  # the deviation's 3x3 mean and the garrote
        up, down, r = _mirrored(u - 1, hc), _mirrored(u + 1, hc), u % n
        for c in range(3):
            _binomial_across(rings[3, up % 3, c], rings[3, u % 3, c], rings[3, down % 3, c], k,
                             deviation[c, r])
        _shrink_row(smoothed, neutral, noise, deviation, r)
    u = t - 4
    if 0 <= u < hc:  # the median and the normalisation
        up, down = max(u - 1, 0), min(u + 1, hc - 1)
        for c in range(3):
            _median_row(smoothed[c, up % n], smoothed[c, u % n], smoothed[c, down % n], out[c, u], columns)
        _normalise_row(out, share, floor, lum, u)


@kernel
def _chroma_pass(pixels, lost, channels, levels, exposures, per_pixel, gain_inv, floor_variance, censor, mean, info,
                 kept, weighted, bound, flags, sums, scratch, k, numerator, denominator, smooth_rings, smooth_row,
                 censored, column, white, share, neutral, floor, spread, taps, values, own, smoothed, own_shares, noise,
                 own_noise, residual, deviation, coarse, out, rings, columns, lum):
    """:func:`chroma` with the white balance given (``white``), in one pass over the cell rows: each step the cells'
    statistics of cell row t (:func:`_cell_stats_row`), their smoothing (:func:`_smooth_step`, row t - 1), the
    censored cells within 3x3 of row t - 2 (:func:`_dilated_row`, ``column`` its scratch) and :func:`_share_step`
    t - 1, so that the statistics, the smoothed sums and the censoring are rings of their last :data:`CELL_ROWS`
    cell rows (``mean`` to ``flags``, ``numerator``, ``denominator``, ``censored``), read while in cache, never
    planes of the frame. The arguments are those of :func:`_cell_pass` (the first 22), the ring of the censored
    cells (rows of the censoring's 3x3 dilation) and its scratch, then those of :func:`_share_pass` (``white`` on);
    bit for bit the chain of the three."""
    hc = out.shape[1]
    for t in range(hc + 5):
        if t < hc:
            _cell_stats_row(pixels, lost, channels, levels, exposures, per_pixel, gain_inv, floor_variance, censor,
                            mean, info, kept, weighted, bound, flags, sums, scratch, t, t % mean.shape[1])
        _smooth_step(weighted, kept, mean, k, numerator, denominator, smooth_rings, smooth_row, t, hc)
        if 0 <= t - 2 < hc:
            _dilated_row(flags[1], t - 2, hc, column, censored[(t - 2) % censored.shape[0]])
        if t >= 1:
            _share_step(numerator, denominator, weighted, kept, mean, info, bound, censored, white, share, neutral,
                        floor, spread, taps, k, values, own, smoothed, own_shares, noise, own_noise, residual,
                        deviation, coarse, out, rings, columns, lum, t - 1)


@kernel
def _dilated_row(flags, i, hc, column, out):
    """out (Wc,) uint8 = the largest of ``flags`` over the 3x3 cells around each cell of cell row ``i`` of ``hc``,
    mirrored at the edges: row i of OpenCV's ``dilate`` with a 3x3 box and BORDER_REFLECT_101, from a ring of the
    last cell rows (``flags`` (R, Wc), cell row j at j % R) inside :func:`_chroma_pass`. ``column``: (Wc,) uint8
    scratch, the largest of each column's three."""
    m, wc = flags.shape
    a, b, c = flags[_mirrored(i - 1, hc) % m], flags[i % m], flags[_mirrored(i + 1, hc) % m]
    for j in range(wc):
        column[j] = max(max(a[j], b[j]), c[j])
    for j in range(1, wc - 1):
        out[j] = max(max(column[j - 1], column[j]), column[j + 1])
    out[0] = max(column[0], column[_mirrored(1, wc)])
    if wc > 1:
        out[wc - 1] = max(column[wc - 1], column[wc - 2])


@kernel(inline="always")
def _mirrored(i, n):
    """Row ``i`` (one beyond the ends at most) of ``n`` mirrored at the ends without repeating them
    (OpenCV's BORDER_REFLECT_101; 0 for a single row)."""
    i = -i if i < 0 else (2 * n - 2 - i if i >= n else i)
    return min(max(i, 0), n - 1)


@kernel
def _taps_along(x, taps, out):
    """out (W,) = 3 ``taps`` along ``x`` (W,), the ends' values repeated: OpenCV's row filter of a
    float32 ``sepFilter2D`` (a fused multiply-add per tap after the first)."""
    w = x.size
    k0, k1, k2 = taps[0], taps[1], taps[2]
    for j in range(1, w - 1):
        out[j] = fma32(x[j + 1], k2, fma32(x[j], k1, x[j - 1] * k0))
    out[0] = fma32(x[min(1, w - 1)], k2, fma32(x[0], k1, x[0] * k0))
    if w > 1:
        out[w - 1] = fma32(x[w - 1], k2, fma32(x[w - 1], k1, x[w - 2] * k0))


@kernel
def _taps_across(a, b, c, taps, out):
    """out (W,) = 3 ``taps`` across the rows ``a``, ``b``, ``c`` (W,): OpenCV's column filter of a float32
    ``sepFilter2D`` (products, then their sum from the first)."""
    k0, k1, k2 = taps[0], taps[1], taps[2]
    for j in range(out.size):
        out[j] = (a[j] * k0 + b[j] * k1) + c[j] * k2


@kernel
def _binomial_along(x, k, out):
    """out (W,) = the symmetric 3 taps ``k`` along ``x`` (W,), mirrored at the ends (BORDER_REFLECT_101):
    OpenCV's symmetric row filter, the outer pair's sum times k_0 plus the centre times k_1."""
    w = x.size
    k0, k1 = k[0], k[1]
    for j in range(1, w - 1):
        out[j] = (x[j - 1] + x[j + 1]) * k0 + x[j] * k1
    out[0] = (x[_mirrored(-1, w)] + x[_mirrored(1, w)]) * k0 + x[0] * k1
    if w > 1:
        out[w - 1] = (x[w - 2] + x[_mirrored(w, w)]) * k0 + x[w - 1] * k1


@kernel
def _binomial_across(a, b, c, k, out):
    """out (W,) = the symmetric 3 taps ``k`` across the rows ``a``, ``b``, ``c`` (W,), as :func:`_binomial_along`."""
    k0, k1 = k[0], k[1]
    for j in range(out.size):
        out[j] = (a[j] + c[j]) * k0 + b[j] * k1


@kernel
def _median_row(a, b, c, out, sorted_columns):
    """out (W,) = the median of the 3x3 values around each column of the rows ``a``, ``b``, ``c`` (W,),
    the end columns repeated (OpenCV's ``medianBlur`` of 3 on float32): each column's three sorted
    (into ``sorted_columns``, (3, W) scratch), then the median of the largest of the smallest, the
    median of the medians and the smallest of the largest of the three columns around."""
    w = out.size
    lo, mid, hi = sorted_columns[0], sorted_columns[1], sorted_columns[2]
    for j in range(w):
        lo[j], mid[j], hi[j] = _sorted3(a[j], b[j], c[j])
    for j in range(1, w - 1):
        out[j] = _median_of(lo[j - 1], lo[j], lo[j + 1], mid[j - 1], mid[j], mid[j + 1], hi[j - 1], hi[j], hi[j + 1])
    out[0] = _median_of(lo[0], lo[0], lo[min(1, w - 1)], mid[0], mid[0], mid[min(1, w - 1)], hi[0], hi[0],
                        hi[min(1, w - 1)])
    if w > 1:
        out[w - 1] = _median_of(lo[w - 2], lo[w - 1], lo[w - 1], mid[w - 2], mid[w - 1], mid[w - 1], hi[w - 2],
                                hi[w - 1], hi[w - 1])


@kernel(inline="always")
def _median_of(lo0, lo1, lo2, mid0, mid1, mid2, hi0, hi1, hi2):
    """The median of 9 values given as three sorted columns (smallest, median, largest of each)."""
    return _sorted3(max(max(lo0, lo1), lo2), _sorted3(mid0, mid1, mid2)[1], min(min(hi0, hi1), hi2))[1]


@kernel(inline="always")
def _sorted3(x, y, z):
    """(smallest, median, largest) of three values."""
    lo, hi = min(x, y), max(x, y)
    return min(lo, z), max(lo, min(hi, z)), max(hi, z)


@kernel
def _shares_row(values, info, bound, censored, share, neutral, floor, spread, coarse, noise, i, g, r):
    """values (3, R, Wc): C_c in, k_c = max(C_c / L, floor) out (a neutral's where L <= 0), in place, for
    cell row ``i``, which is row ``r`` of ``values`` and ``noise`` (rings of cell rows, or whole planes with
    ``r`` = ``i``), row ``g`` of ``info``, ``bound`` and ``censored`` (the same) and row ``i`` of ``coarse``.

    ``coarse`` (2, Hc, Wc): L and its variance sum_c n_c^2 v_c, v_c = spread / info_c the variance
    of C_c (``spread``: the sum of the squared weights of the cells' smoothing; 1 for a cell with
    censored readings, ``bound`` > 0, which keeps its own), COARSE_NONE where ``censored`` (Hc, Wc)
    is set. ``noise`` (3, R, Wc): v_c / L^2, the variance of k_c from C_c's noise. Loops over the
    cells of the row (which vectorise).
    """
    zero, one, none = np.float32(0.0), np.float32(1.0), np.float32(COARSE_NONE)
    tiny = np.float32(1e-30)
    lum_row, var = coarse[0, i], coarse[1, i]
    red, green, blue = values[0, r], values[1, r], values[2, r]
    for j in range(lum_row.size):
        lum_row[j] = share[0] * red[j] + share[1] * green[j] + share[2] * blue[j]
        var[j] = zero
    for c in range(3):
        k, n, inf, level, weight = values[c, r], noise[c, r], info[c, g], neutral[c], share[c]
        b = bound[c, g]
        for j in range(lum_row.size):
            ok = lum_row[j] > zero
            inverse = one / lum_row[j] if ok else zero
            v = (spread if b[j] <= zero else one) / max(inf[j], tiny)
            kc = max(k[j] * inverse, floor) if ok else level
            k[j] = kc
            n[j] = min(v * inverse * inverse, none) if ok else none
            var[j] += weight * weight * v
    lost = censored[g]
    for j in range(lum_row.size):
        var[j] = none if lost[j] else min(var[j], none)


@kernel
def _own_shares_row(values, info, share, neutral, floor, smoothed, noise, residual, lum, i, r):
    """values (3, R, Wc): each cell's own C_c in, its shares k_c = max(C_c / L, floor) out (a
    neutral's where L <= 0), in place, for cell row ``i`` (row ``r`` of the (3, R, Wc) planes, row ``i``
    of ``info``), as :func:`_shares_row` with the cell's own readings alone (their variance 1 / info_c;
    ``noise``: v_c / L^2, at most COARSE_NONE). ``residual`` (out): (k_c - ``smoothed``_c)^2. ``lum``:
    (Wc,) scratch."""
    zero, one, none, tiny = np.float32(0.0), np.float32(1.0), np.float32(COARSE_NONE), np.float32(1e-30)
    red, green, blue = values[0, r], values[1, r], values[2, r]
    for j in range(lum.size):
        lum[j] = share[0] * red[j] + share[1] * green[j] + share[2] * blue[j]
    for c in range(3):
        k, n, e, inf, ks, level = values[c, r], noise[c, r], residual[c, r], info[c, i], smoothed[c, r], neutral[c]
        for j in range(lum.size):
            ok = lum[j] > zero
            inverse = one / lum[j] if ok else zero
            v = one / max(inf[j], tiny)
            kc = max(k[j] * inverse, floor) if ok else level
            k[j] = kc
            n[j] = min(v * inverse * inverse, none) if ok else none
            e[j] = (kc - ks[j]) * (kc - ks[j])


@kernel
def _blend_row(shares, noise, own, own_noise, residual, neutral, deviation, i):
    """The smoothed shares of cell row ``i`` moved towards each cell's own where they differ beyond noise,
    in place.

    ``shares`` and ``noise`` (3, R, Wc), every plane here rows of cell rows (rings, or whole planes): the
    shares of the 3x3 cells' smoothed values and their variance v_s; ``own`` and ``own_noise``: those of each cell's own readings, v_o. The smoothed
    estimate holds the own readings, so own - smoothed has variance v_o - v_s (nested
    inverse-variance estimates, as :func:`refine`) plus the squared difference of what they
    estimate, which ``residual`` (the 3x3 cells' mean of (own - smoothed)^2) measures:
    k = k_s + beta (k_o - k_s), beta = max(0, 1 - t / E), t = max(v_o - v_s, 0); the variance
    becomes v_s + beta t. Colour finer than the 3x3 cells is kept where the readings show it
    beyond their noise (bright scenes), and the dark keeps the smoothed shares. ``deviation``
    (out): (k_c - neutral_c)^2.
    """
    zero, one, tiny = np.float32(0.0), np.float32(1.0), np.float32(1e-30)
    for c in range(3):
        level = neutral[c]
        k, v, ko, vo, e, d = shares[c, i], noise[c, i], own[c, i], own_noise[c, i], residual[c, i], deviation[c, i]
        for j in range(k.size):
            t = max(vo[j] - v[j], zero)
            beta = max(one - t / max(e[j], tiny), zero)
            kc = k[j] + beta * (ko[j] - k[j])
            k[j] = kc
            v[j] += beta * t
            d[j] = (kc - level) * (kc - level)


@kernel
def _shrink_row(shares, neutral, noise, deviation, i):
    """Shares of cell row ``i`` towards the neutral's where their deviation from it is within their noise,
    in place: k_c = neutral_c + beta_c (k_c - neutral_c), beta_c = max(0, 1 - noise_c / E_c) with E_c the
    3x3 cells' mean squared deviation (``deviation``, smoothed).

    The chroma's own garrote (as :func:`refine`'s for luminance): a colour is kept where the
    cells around show it beyond the noise, and noise in the dark is not painted as colour.
    """
    zero, one, tiny = np.float32(0.0), np.float32(1.0), np.float32(1e-30)
    for c in range(3):
        k, n, d, level = shares[c, i], noise[c, i], deviation[c, i], neutral[c]
        for j in range(k.size):
            beta = max(one - n[j] / max(d[j], tiny), zero)
            k[j] = level + beta * (k[j] - level)


@kernel
def _normalise_row(shares, share, floor, total, i):
    """Shares (3, Hc, Wc) of cell row ``i`` scaled so that sum_c n_c k_c = 1 in each cell, then at least
    ``floor``, in place. ``total``: (Wc,) scratch."""
    zero, one = np.float32(0.0), np.float32(1.0)
    total[:] = zero
    for c in range(3):
        k, weight = shares[c, i], share[c]
        for j in range(k.size):
            total[j] += weight * k[j]
    for j in range(total.size):
        total[j] = one / total[j]
    for c in range(3):
        k = shares[c, i]
        for j in range(k.size):
            k[j] = max(k[j] * total[j], floor)
