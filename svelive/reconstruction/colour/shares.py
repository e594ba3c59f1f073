"""The chroma at cell resolution (svelive.reconstruction.colour, step a): each channel's cell values
smoothed over 3x3 cells and moved to the cells' centres, the shares k_c = C_c / L and the coarse
luminance, the blend towards each cell's own shares and the garrote towards the neutral, the median over
3x3 cells and the normalisation (:func:`chroma`)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from svelive.jit import kernel
from svelive.reconstruction.colour.cells import CellLayout, _cell_stats, cell_layout
from svelive.reconstruction.colour.highlights import _cell_values, white_balance
from svelive.reconstruction.methods.base import SveInput, binomial_kernel

#: A channel's share of luminance is at least this (a zero would make its pixels' exposure 0).
SHARE_FLOOR = 1e-3
#: Variance standing for "no coarse luminance here" (finite, so that interpolating it stays large).
COARSE_NONE = 1e30


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

    def fused(self, planes: np.ndarray) -> Chroma:
        """The same chroma with a stream's fused shares and coarse luminance, (5, Hc, Wc) planes."""
        return Chroma(planes[:3], planes[3:5], self.layout, self.white, self.shape)


def chroma(inp: SveInput) -> Chroma:
    """The chroma of a colour frame (package docstring, step a), at cell resolution.

    Each channel's cell means are smoothed over 3x3 cells ([1, 2, 1] / 4 each way, weighted by
    the share of each cell's information its uncensored readings hold, the smallest over the
    channels: :func:`_smooth_cells`), the censoring and
    highlight rules give C_c, which is moved from the centroid of the channel's samples to the
    cells' centres (bilinearly), and the shares are k_c = C_c / L there. The same from each
    cell's own readings moves them where the two differ beyond noise (:func:`_blend`), the
    garrote towards the neutral follows (:func:`_shrink`), then each channel's median over 3x3
    cells (a cell straddling an edge is an outlier) and the scaling to sum_c n_c k_c = 1.
    """
    layout = cell_layout(inp.pattern, inp.cfa)
    (cy, cx), (h, w) = layout.cell, inp.shape
    hc, wc = -(-h // cy), -(-w // cx)
    f32 = np.float32
    mean, info, kept, weighted, bound = (np.empty((3, hc, wc), f32) for _ in range(5))
    flags = np.empty((2, hc, wc), np.uint8)
    sensor = inp.sensor
    per_pixel = inp.pattern.pixel_map is not None
    values = inp.signal / inp.exposure if per_pixel else inp.signal
    _cell_stats(values, inp.censored, layout.channels, layout.levels, layout.exposures,
                per_pixel, f32(1.0 / sensor.effective_gain), f32(sensor.floor_variance), f32(sensor.censor_level),
                mean, info, kept, weighted, bound, flags, np.empty((3, 3, layout.exposures.size, wc), f32),
                np.empty((6, wc), f32))
    k = binomial_kernel(3)
    spread = f32(np.sum(k * k) ** 2)  # the sum of the squared weights of the cells' smoothing
    numerator, denominator = np.empty((3, hc, wc), f32), np.empty((3, hc, wc), f32)
    _smooth_cells(weighted, kept, mean, k, numerator, denominator)
    box = np.ones((3, 3), np.uint8)  # within 3x3 cells of: a channel with only censored readings, any censored
    clipped, censored = (cv2.dilate(flags[k], box, borderType=cv2.BORDER_REFLECT_101) for k in range(2))
    white = white_balance(numerator, denominator, info, clipped, layout.share, spread)
    values, own = np.empty((3, hc, wc), f32), np.empty((3, hc, wc), f32)
    # the smoothed values, and each cell's own readings' (own), in one pass over the cells' statistics
    _cell_values(numerator, denominator, weighted, kept, mean, info, bound, white, values, own, np.empty(wc, f32))
    shares, own_shares = _centred(values, layout), _centred(own, layout)
    neutral = (white / f32(layout.share @ white)).astype(f32)
    coarse = np.empty((2, hc, wc), f32)
    noise, own_noise, deviation, residual = (np.empty((3, hc, wc), f32) for _ in range(4))
    _shares(shares, info, bound, censored, layout.share, neutral, f32(SHARE_FLOOR), spread, coarse, noise, deviation,
            own_shares, own_noise, residual, np.empty(wc, f32))
    for c in range(3):
        cv2.sepFilter2D(residual[c], cv2.CV_32F, k, k, dst=residual[c], borderType=cv2.BORDER_REFLECT_101)
    _blend(shares, noise, own_shares, own_noise, residual, neutral, deviation)
    for c in range(3):
        cv2.sepFilter2D(deviation[c], cv2.CV_32F, k, k, dst=deviation[c], borderType=cv2.BORDER_REFLECT_101)
    _shrink(shares, neutral, noise, deviation)
    for c in range(3):  # a cell whose channels read different sides of an edge is an outlier among its neighbours
        cv2.medianBlur(shares[c], 3, dst=shares[c])
    _normalise(shares, layout.share, f32(SHARE_FLOOR), np.empty(wc, f32))
    return Chroma(shares, coarse, layout, white, (h, w))


def _smooth_cells(weighted: np.ndarray, kept: np.ndarray, mean: np.ndarray, k: np.ndarray,
                  numerator: np.ndarray, denominator: np.ndarray) -> None:
    """The sums of the cells' 3x3 smoothing (3, Hc, Wc), in place: every channel of a cell weighted
    alike, by the smallest share of a channel's information its uncensored readings hold in it.

    Per channel (``kept`` of each) a cell beside a light that clipped some channels gave its
    unclipped channels in full and its clipped ones at the share of their unclipped (darker)
    readings: on dual-ISO a 3x3 orange light whose red and green clip the long rows spread its
    blue, measured there, into the dark cells around, whose shares turned violet (blue 5.5 times
    the luminance) and the 3x3 median carried that into the light. With one weight for every
    channel the ratios the smoothing forms are those of the cells it averages. Where that weight is
    0 for every cell around (a channel with only censored readings in each), each channel keeps
    the cell's own readings (the highlight rules take the censored ones)."""
    common = kept.min(axis=0)
    products = common * mean
    for c in range(3):
        cv2.sepFilter2D(products[c], cv2.CV_32F, k, k, dst=numerator[c], borderType=cv2.BORDER_REFLECT_101)
    cv2.sepFilter2D(common, cv2.CV_32F, k, k, dst=denominator[0], borderType=cv2.BORDER_REFLECT_101)
    denominator[1:] = denominator[0]
    none = np.nonzero(denominator[0] <= 0)
    if none[0].size:
        for c in range(3):
            numerator[c][none], denominator[c][none] = weighted[c][none], kept[c][none]


def _centred(values: np.ndarray, layout: CellLayout) -> np.ndarray:
    """Cell values (3, Hc, Wc) moved from the centroid of each channel's samples to the cells'
    centres (bilinearly, :func:`_centring_kernels`), float32 (3, Hc, Wc)."""
    out = np.empty_like(values)
    for c, (ky, kx) in enumerate(_centring_kernels(layout)):
        cv2.sepFilter2D(values[c], cv2.CV_32F, kx, ky, dst=out[c], borderType=cv2.BORDER_REPLICATE)
    return out


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


@kernel
def _shares(values, info, bound, censored, share, neutral, floor, spread, coarse, noise, deviation,
            own, own_noise, residual, lum):
    """values (3, Hc, Wc): C_c in, k_c = max(C_c / L, floor) out (a neutral's where L <= 0), in place.

    ``coarse`` (2, Hc, Wc): L and its variance sum_c n_c^2 v_c, v_c = spread / info_c the variance
    of C_c (``spread``: the sum of the squared weights of the cells' smoothing; 1 for a cell with
    censored readings, ``bound`` > 0, which keeps its own), COARSE_NONE where ``censored`` (Hc, Wc)
    is set. ``noise`` (3, Hc, Wc): v_c / L^2, the variance of k_c from C_c's
    noise; ``deviation``: (k_c - neutral_c)^2. ``own`` (3, Hc, Wc): each cell's own C_c in, its
    shares out (:func:`_own_shares_row`, ``own_noise`` and ``residual``), cell row by cell row
    after the smoothed ones while the row's are in cache. ``lum``: (Wc,) scratch. Loops over the
    cells of a row (which vectorise).
    """
    zero, one, none = np.float32(0.0), np.float32(1.0), np.float32(COARSE_NONE)
    tiny = np.float32(1e-30)
    for i in range(values.shape[1]):
        lum_row, var = coarse[0, i], coarse[1, i]
        r, g, b = values[0, i], values[1, i], values[2, i]
        for j in range(lum_row.size):
            lum_row[j] = share[0] * r[j] + share[1] * g[j] + share[2] * b[j]
            var[j] = zero
        for c in range(3):
            k, n, d, inf, level, weight = values[c, i], noise[c, i], deviation[c, i], info[c, i], neutral[c], share[c]
            b = bound[c, i]
            for j in range(lum_row.size):
                ok = lum_row[j] > zero
                inverse = one / lum_row[j] if ok else zero
                v = (spread if b[j] <= zero else one) / max(inf[j], tiny)
                kc = max(k[j] * inverse, floor) if ok else level
                k[j] = kc
                n[j] = min(v * inverse * inverse, none) if ok else none
                d[j] = (kc - level) * (kc - level)
                var[j] += weight * weight * v
        lost = censored[i]
        for j in range(lum_row.size):
            var[j] = none if lost[j] else min(var[j], none)
        _own_shares_row(own, info, share, neutral, floor, values, own_noise, residual, lum, i)


@kernel
def _own_shares_row(values, info, share, neutral, floor, smoothed, noise, residual, lum, i):
    """values (3, Hc, Wc): each cell's own C_c in, its shares k_c = max(C_c / L, floor) out (a
    neutral's where L <= 0), in place, for cell row ``i``, as :func:`_shares` with the cell's own
    readings alone (their variance 1 / info_c; ``noise``: v_c / L^2, at most COARSE_NONE).
    ``residual`` (out): (k_c - ``smoothed``_c)^2. ``lum``: (Wc,) scratch."""
    zero, one, none, tiny = np.float32(0.0), np.float32(1.0), np.float32(COARSE_NONE), np.float32(1e-30)
    r, g, b = values[0, i], values[1, i], values[2, i]
    for j in range(lum.size):
        lum[j] = share[0] * r[j] + share[1] * g[j] + share[2] * b[j]
    for c in range(3):
        k, n, e, inf, ks, level = values[c, i], noise[c, i], residual[c, i], info[c, i], smoothed[c, i], neutral[c]
        for j in range(lum.size):
            ok = lum[j] > zero
            inverse = one / lum[j] if ok else zero
            v = one / max(inf[j], tiny)
            kc = max(k[j] * inverse, floor) if ok else level
            k[j] = kc
            n[j] = min(v * inverse * inverse, none) if ok else none
            e[j] = (kc - ks[j]) * (kc - ks[j])


@kernel
def _blend(shares, noise, own, own_noise, residual, neutral, deviation):
    """The smoothed shares moved towards each cell's own where they differ beyond noise, in place.

    ``shares`` and ``noise`` (3, Hc, Wc): the shares of the 3x3 cells' smoothed values and their
    variance v_s; ``own`` and ``own_noise``: those of each cell's own readings, v_o. The smoothed
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
        for i in range(shares.shape[1]):
            k, v, ko, vo, e, d = shares[c, i], noise[c, i], own[c, i], own_noise[c, i], residual[c, i], deviation[c, i]
            for j in range(k.size):
                t = max(vo[j] - v[j], zero)
                beta = max(one - t / max(e[j], tiny), zero)
                kc = k[j] + beta * (ko[j] - k[j])
                k[j] = kc
                v[j] += beta * t
                d[j] = (kc - level) * (kc - level)


@kernel
def _shrink(shares, neutral, noise, deviation):
    """Shares towards the neutral's where their deviation from it is within their noise, in place:
    k_c = neutral_c + beta_c (k_c - neutral_c), beta_c = max(0, 1 - noise_c / E_c) with E_c the
    3x3 cells' mean squared deviation (``deviation``, smoothed).

    The chroma's own garrote (as :func:`refine`'s for luminance): a colour is kept where the
    cells around show it beyond the noise, and noise in the dark is not painted as colour.
    """
    zero, one, tiny = np.float32(0.0), np.float32(1.0), np.float32(1e-30)
    for i in range(shares.shape[1]):
        for c in range(3):
            k, n, d, level = shares[c, i], noise[c, i], deviation[c, i], neutral[c]
            for j in range(k.size):
                beta = max(one - n[j] / max(d[j], tiny), zero)
                k[j] = level + beta * (k[j] - level)


@kernel
def _normalise(shares, share, floor, total):
    """Shares (3, Hc, Wc) scaled so that sum_c n_c k_c = 1 in each cell, then at least ``floor``,
    in place. ``total``: (Wc,) scratch."""
    zero, one = np.float32(0.0), np.float32(1.0)
    for i in range(shares.shape[1]):
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
