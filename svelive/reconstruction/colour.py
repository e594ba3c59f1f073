"""Colour SVE: a mosaic of colour filters and exposures in, linear camera RGB out.

Every pixel i reads s_i = e_i L_c(i) (plus noise): its exposure times the
radiance of its own colour channel c(i). Two ways to reconstruct (``mode``):

``"split"``, the baseline the issue asks for: HDR per colour channel with a
monochrome method, then demosaicing. The frame is split into its CFA-phase
sub-images (for a CFA of same-colour blocks, such as quad-RGGB, into sub-images
of whole blocks, so that each keeps the block's exposures), each with its own
sub-pattern of exposures (RGGB + ``1/1/8/8`` gives four quarter images with the
pattern ``1/8``); the method reconstructs each, the results go back to their
pixels as an HDR mosaic, and the mosaic is demosaiced. OpenCV demosaics only 8-
and 16-bit data, so the mosaic is log-encoded to 16 bits (log2 of radiance plus
the longest exposure's noise floor, over the frame's range: a step of well under
0.1 % of a value), demosaiced, and decoded: interpolating log radiance suits HDR
data, where linear interpolation across an edge of a thousand to one smears the
bright side over the dark (measured on the shipped crops, dual-ISO at bright
exposure: up to 1 dB PU21 better than linear-domain bilinear interpolation,
nowhere worse by more than 0.05 dB). A Bayer CFA goes through OpenCV's
edge-aware conversion (``COLOR_Bayer...2RGB_EA``).
A CFA that is not a 2x2 Bayer tile (quad-RGGB, custom tiles) has no OpenCV
demosaicing: there each channel is interpolated by normalised convolution with a
separable tent as wide as the CFA's period (bilinear for Bayer), in the same log
encoding. No noise model and no highlight rule beyond the mono method's.

``"joint"``, the default: colour is the low-resolution part of the problem,
luminance the full-resolution part, and the noise model serves both.

(a) Chroma. Over the cells of the joint tile (exposure pattern and CFA: 4x2
for dual-ISO, 4x4 for quad-Bayer), each channel's uncensored readings x = s / e
are averaged with inverse-variance weights e_k^2 / (e_k L0 / g + sigma^2) of
the noise model at a pilot L0 (the channel's shot-noise estimate sum s / sum e
in the cell), then smoothed over the 3x3 neighbouring cells ([1, 2, 1] / 4 each
way) weighted by the share of each cell's information its uncensored readings
hold (1 without censoring). Not by the cells' information itself: evaluated at
each cell's own pilot it is larger for darker cells (1 / L in the shot-noise
regime), which biased every edge towards its dark side and cost 2 dB PU21.
Each channel's cell value stands for the centroid of its samples in the cell
(weights e, the shot-limited ones) and is moved to the cells' centres by
bilinear interpolation over the cells: without that, channels sampled half a
cell apart read different points of any edge, which is false colour at every
neutral edge. At the centres, L = sum_c n_c C_c (n_c the channel's share of the
CFA tile: 1/4, 1/2, 1/4 for Bayer) and the shares k_c = C_c / L. The same
shares from each cell's own readings alone (unsmoothed, centred alike) hold
colour finer than 3x3 cells: the smoothed shares move towards them by the
garrote of (b') below where the two differ beyond their noise (the variance of
own - smoothed is v_own - v_smoothed for nested estimates; the evidence is the
3x3 cells' mean squared difference), so bright scenes keep fine colour and the
dark keeps the smoothed shares. Where a
share's deviation from a neutral surface's is within its noise over the 3x3
cells (the colour noise of dark regions), it is shrunk towards the neutral by
the same garrote: noise in the dark is not painted as colour (5 stops
dim, dual-ISO, mean of the shipped crops: CIEDE2000 mean 8.6 -> 7.8, p99
21.7 -> 20.4; PU21 on luminance unchanged). Last, each channel's shares take
the median of the 3x3 cells around, and are scaled back to sum_c n_c k_c = 1.
A cell whose channels read different sides of an edge (its samples sit at
different places in the cell, and the centring and smoothing shift each
channel's profile of the edge differently) has shares that neither side has:
up to twice the neutral's at a black/white edge, and the luminance folded with
them alternated from pixel to pixel along the edge (zipper). Among its
neighbours such a cell is an outlier, and a median rejects it while it keeps
an edge between two colours (a straight edge keeps the majority of the 3x3
cells on each side); colour features narrower than two cells go. Measured
(neutral black/white edge of docs/stability.md, luminance error within 3 px at
2 stops): dual-ISO 0.150 -> 0.036 stop (split 0.061), column-Bayer 0.156 ->
0.041 (0.062), assorted-4x4 0.151 -> 0.067 (0.077), quad-Bayer 0.193 -> 0.045
(0.247). All of
this is computed at cell resolution and interpolated bilinearly on the fly by
the compiled passes below (no full-resolution chroma planes are written).

(b) Luminance as a monochrome SVE problem. Pixel i reads
s_i = e_i L_c = (e_i k_c) Y where the chroma is right: the mosaic is a
monochrome SVE frame of the luminance Y = sum_c n_c L_c whose effective
exposure e'_i = e_i k_c(i) varies per pixel (SveInput.folded). The signal is
the raw signal, so censoring and the Poisson-Gaussian noise model hold as
they are; the chosen mono method (``adaptive`` by default) reconstructs Y at
full resolution with its own rules for noise, edges, censoring and lower
bounds. Where the chroma is locally wrong (a colour edge inside the chroma's
support), one channel's readings disagree with their neighbours beyond their
noise, and ``adaptive`` keeps each pixel's own reading there, as at any edge.
A method that reads only the pattern's tile (MethodSpec.exposures is False:
``aggregate``) gets the readings divided by k_c instead, exact below
saturation, approximate at it.

(b') Refinement at the chroma's scale (methods that report their variance).
The cells also give a coarse luminance L with a small variance; the fine Y is
moved towards it by a noise-model garrote (:func:`refine`) where the two differ
by no more than Y's noise: in the read-noise regime a full-resolution estimate
is mostly noise, and the mono method's window alone averages too few readings
there (on the shipped crops 5 stops dim, +0.7 to +1.9 dB PU21 on the two
noise-limited scenes, -0.6 dB on the third, within 0.3 dB at bright exposure).

(c) RGB = Y k_c for each channel c, with the same k_c as the folding (so at a
pixel whose own reading decided Y, its own channel is that reading).

Highlights. Where a channel has censored readings in a cell, its uncensored
neighbours are the darker ones, so the cell keeps its own readings (at least
their bound); where it has censored readings and no uncensored one, its value
is only a lower bound, and a clipped channel kept at its bound beside measured
ones is what makes clipped highlights magenta or pink (green, the most
sensitive channel, clips first). So such a channel is raised to at least the
white-balanced level of the brightest measured channel of the cell,
max(bound, white_c max_m C_m / white_m): a highlight that clipped some channels
goes neutral (white), never magenta; a saturated colour whose measured channels
are darker keeps its bound. Where every channel is censored, all take the
neutral white at the largest bound (white_c max_m bound_m / white_m), and the
mono method flags Y as a lower bound there. The white balance is the median,
over about 4096 cells whose smoothed luminance is measured to 10 % (an SNR of
10 by the noise model) and away from channels with only censored readings, of
C_R / C_G and C_B / C_G: robust to coloured objects; used for highlights and as
the neutral of the chroma's garrote. (Choosing cells by each channel's own SNR
favoured cells where that channel read high: 10 % too red and blue on a dark
grey frame. Too few cells, or none where a 64x exposure clips over a whole
bright ground, left it at 1, 1, 1: highlights went magenta.)

Known limit: the chroma is that of cells (4x2 pixels for dual-ISO), so colour
that changes within a few pixels (thin coloured lines, fine colour texture)
is folded with the cells' shares, and the luminance there inherits their
error: with the true shares of every pixel the luminance would be about 2 dB
PU21 better on the shared images at bright exposure. On a neutral edge the
zipper is gone (above); at 1 stop of contrast on assorted-4x4 the luminance
error near the edge is still 0.074 stop against the baseline's 0.062.

Units: radiance in DN at relative exposure 1 per channel (before white
balance); the luminance Y in that unit, which ``variance`` and
``lower_bound`` of the result describe.
"""

from __future__ import annotations

from concurrent.futures import Executor
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from numba import types
from numba.extending import intrinsic

from svelive.core.camera import colour_phase
from svelive.core.cfa import ColourFilter, joint_period
from svelive.core.errors import SveliveError
from svelive.core.pattern import Pattern
from svelive.jit import kernel
from svelive.reconstruction.methods import MethodSpec
from svelive.reconstruction.methods.base import Estimate, SveInput, binomial_kernel, exposure_maps, map_on, smooth

MODES = ("joint", "split")
#: A channel's share of luminance is at least this (a zero would make its pixels' exposure 0).
SHARE_FLOOR = 1e-3
#: Variance standing for "no coarse luminance here" (finite, so that interpolating it stays large).
COARSE_NONE = 1e30
#: Cells whose every channel is measured to 1 / WHITE_SNR (relative standard deviation) give the white balance.
WHITE_SNR = 10.0
#: Fewer such cells than this: no white balance (neutral is 1, 1, 1).
WHITE_MIN_CELLS = 16
#: About this many cells are looked at for the white balance (every n-th row and column of cells: a
#: median needs no more, and a small frame's every cell counts).
WHITE_CELLS = 4096


def run_colour(inp: SveInput, spec: MethodSpec, mode: str, **options) -> Estimate:
    """Reconstruct a colour frame (``inp.cfa`` set) with the mono method ``spec``.

    Args:
        inp: a prepared colour frame (svelive.reconstruction.input.prepare).
        spec: the monochrome method, with ``options`` (its own, plus ``return_variance``
            and ``workers`` where it has them).
        mode: ``"joint"`` or ``"split"`` (module docstring).

    Returns:
        Estimate with ``image`` float32 (H, W, 3) linear camera RGB (DN at exposure 1 per
        channel, before white balance), ``luminance`` float32 (H, W), the luminance
        Y = sum_c n_c RGB_c, and ``lower_bound`` (H, W) and ``variance`` (H, W) of it.
    """
    if inp.cfa is None:
        raise SveliveError("run_colour needs a colour frame: give the colour filter (cfa='RGGB')")
    if mode == "joint":
        return joint(inp, spec, **options).estimate
    if mode == "split":
        return split(inp, spec, **options)
    raise SveliveError(f"unknown colour mode {mode!r}; choose from {', '.join(MODES)}")


# ----- layout of the cells ----------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class CellLayout:
    """What the pattern and the CFA alone fix for the chroma's cells (cached, read-only).

    Attributes:
        cell: (rows, cols) of a cell: the joint tile of exposure pattern and CFA.
        channels: uint8 (rows, cols), the channel of each pixel of a cell.
        levels: uint8 (rows, cols), the index into ``exposures`` of each pixel's nominal exposure.
        exposures: float32 (K,), the pattern's exposure levels.
        share: float32 (3,), n_c, each channel's share of the CFA tile.
        origin: float64 (3, 2), (row, col) within a cell of the centroid of each channel's
            samples, weighted by their nominal exposure (the weights of sum s / sum e).
    """

    cell: tuple[int, int]
    channels: np.ndarray
    levels: np.ndarray
    exposures: np.ndarray
    share: np.ndarray
    origin: np.ndarray

    @property
    def centre(self) -> np.ndarray:
        """float64 (2,), the (row, col) of a cell's centre within it."""
        return (np.array(self.cell, np.float64) - 1) / 2


@lru_cache(maxsize=16)
def cell_layout(pattern: Pattern, cfa: ColourFilter) -> CellLayout:
    """The :class:`CellLayout` of a pattern (its nominal tile) and a CFA."""
    cell = joint_period(pattern.shape, cfa.shape)
    nominal = Pattern(pattern.tile)
    channels = cfa.channel_map(cell)
    levels = nominal.level_index_map(cell)
    exposure = nominal.exposure_map(cell).astype(np.float64)
    share = np.array([np.mean(cfa.tile == c) for c in range(3)], np.float32)
    rows, cols = np.mgrid[:cell[0], :cell[1]]
    origin = np.empty((3, 2))
    for c in range(3):
        weight = exposure * (channels == c)
        origin[c] = (weight * rows).sum() / weight.sum(), (weight * cols).sum() / weight.sum()
    layout = CellLayout(cell, channels, levels, nominal.levels.astype(np.float32), share, origin)
    for array in (channels, levels, layout.exposures, share, origin):
        array.setflags(write=False)
    return layout


# ----- chroma -------------------------------------------------------------------------------

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
    """The chroma of a colour frame (module docstring, step a), at cell resolution.

    Each channel's cell means are smoothed over 3x3 cells ([1, 2, 1] / 4 each way, weighted by
    the share of each cell's information its uncensored readings hold), the censoring and
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
    for c in range(3):
        cv2.sepFilter2D(weighted[c], cv2.CV_32F, k, k, dst=numerator[c], borderType=cv2.BORDER_REFLECT_101)
        cv2.sepFilter2D(kept[c], cv2.CV_32F, k, k, dst=denominator[c], borderType=cv2.BORDER_REFLECT_101)
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
def _cell_stats(values, censored, channels, levels, exposures, per_pixel, gain_inv, floor, censor,
                mean, info, kept, weighted_mean, bound, flags, sums, scratch):
    """Per cell (cy, cx) = channels.shape and channel, (3, Hc, Wc) each: the inverse-variance mean
    of the uncensored readings x = s / e (``mean``), the sum of their weights (``info``, 0: none),
    the share of the cell's information they hold (``kept``: info over the weights of all its
    readings, 1 without censored ones), ``kept`` times ``mean`` (``weighted_mean``), and the
    largest bound censor / e_k the censored ones imply (``bound``, 0: none). ``flags`` (2, Hc, Wc)
    uint8: 1 where (0) a channel has only censored readings, (1) any reading is censored.
    ``sums`` (3, 3, K, Wc) and ``scratch`` (6, Wc): scratch.

    ``values``: the readings s (H, W), or x itself with ``per_pixel`` exposures (a calibrated
    map). Weights e_k^2 / (e_k L0 / g + sigma^2) of each reading's nominal level e_k, at the pilot
    L0 = max(sum s / sum e, 0) of the channel in the cell. One pass over the pixels, per channel
    and level: the sum of the uncensored values, their count, and the count of all readings.
    """
    h, w = values.shape
    cy, cx = channels.shape
    zero, one = np.float32(0.0), np.float32(1.0)
    x_sum, n_sum, all_sum = sums[0], sums[1], sums[2]
    for i in range(mean.shape[1]):
        r0, r1 = i * cy, min(i * cy + cy, h)
        sums[...] = zero
        for r in range(r0, r1):
            ch, k, row, lost = channels[r - r0], levels[r - r0], values[r], censored[r]
            # the cells of common widths spelt out: loops whose loads LLVM vectorises
            if cx == 2 and w % 2 == 0:
                _add_pairs(row, lost, x_sum[ch[0], k[0]], n_sum[ch[0], k[0]], all_sum[ch[0], k[0]],
                           x_sum[ch[1], k[1]], n_sum[ch[1], k[1]], all_sum[ch[1], k[1]])
                continue
            if cx == 4 and w % 4 == 0:
                for half in range(2):
                    a, b = 2 * half, 2 * half + 1
                    _add_pairs_of_four(row, lost, half, x_sum[ch[a], k[a]], n_sum[ch[a], k[a]],
                                       all_sum[ch[a], k[a]], x_sum[ch[b], k[b]], n_sum[ch[b], k[b]],
                                       all_sum[ch[b], k[b]])
                continue
            for px in range(min(cx, w)):
                xs, ns, alls = x_sum[ch[px], k[px]], n_sum[ch[px], k[px]], all_sum[ch[px], k[px]]
                for j in range((w - px + cx - 1) // cx):
                    keep = zero if lost[j * cx + px] else one
                    xs[j] += row[j * cx + px] * keep
                    ns[j] += keep
                    alls[j] += one
        flags[:, i, :] = 0
        for ch in range(3):  # per channel, loops over the cells of the row (which vectorise)
            s_total, e_total, pilot = scratch[0], scratch[1], scratch[2]
            weighted, total, full = scratch[3], scratch[4], scratch[5]
            b = bound[ch, i]
            scratch[...] = zero
            b[:] = zero
            for k in range(exposures.size):
                e, xs, ns, alls = exposures[k], x_sum[ch, k], n_sum[ch, k], all_sum[ch, k]
                inverse = one if per_pixel else one / e  # sums of s: x = s / e_k
                lost_bound = censor / e
                for j in range(xs.size):
                    xs[j] *= inverse
                    s_total[j] += xs[j] * e
                    e_total[j] += ns[j] * e
                    b[j] = max(b[j], lost_bound if alls[j] > ns[j] else zero)
            for j in range(pilot.size):
                pilot[j] = max(s_total[j] / e_total[j], zero) * gain_inv if e_total[j] > zero else zero
            for k in range(exposures.size):
                e, xs, ns, alls = exposures[k], x_sum[ch, k], n_sum[ch, k], all_sum[ch, k]
                for j in range(xs.size):
                    weight = e * e / (e * pilot[j] + floor)
                    weighted[j] += weight * xs[j]
                    total[j] += weight * ns[j]
                    full[j] += weight * alls[j]
            m, n, kp, km = mean[ch, i], info[ch, i], kept[ch, i], weighted_mean[ch, i]
            for j in range(m.size):
                ok = total[j] > zero
                m[j] = weighted[j] / total[j] if ok else zero
                n[j] = total[j]
                kp[j] = total[j] / full[j] if ok else zero
                km[j] = weighted[j] / full[j] if ok else zero
            clipped, lost = flags[0, i], flags[1, i]
            for j in range(m.size):
                some = b[j] > zero
                clipped[j] |= np.uint8(some and total[j] <= zero)
                lost[j] |= np.uint8(some)


@kernel
def _add_pairs(row, lost, xs0, ns0, alls0, xs1, ns1, alls1):
    """Cells of 2 columns: the row's even pixels into the first sums, odd ones into the second."""
    zero, one = np.float32(0.0), np.float32(1.0)
    for j in range(row.size // 2):
        keep0 = zero if lost[2 * j] else one
        keep1 = zero if lost[2 * j + 1] else one
        xs0[j] += row[2 * j] * keep0
        ns0[j] += keep0
        alls0[j] += one
        xs1[j] += row[2 * j + 1] * keep1
        ns1[j] += keep1
        alls1[j] += one


@kernel
def _add_pairs_of_four(row, lost, half, xs0, ns0, alls0, xs1, ns1, alls1):
    """Cells of 4 columns: pixels 2 half and 2 half + 1 of each into the first and second sums."""
    zero, one = np.float32(0.0), np.float32(1.0)
    a, b = 2 * half, 2 * half + 1
    for j in range(row.size // 4):
        keep0 = zero if lost[4 * j + a] else one
        keep1 = zero if lost[4 * j + b] else one
        xs0[j] += row[4 * j + a] * keep0
        ns0[j] += keep0
        alls0[j] += one
        xs1[j] += row[4 * j + b] * keep1
        ns1[j] += keep1
        alls1[j] += one


@kernel
def _cell_values(numerator, denominator, weighted, kept, mean, info, bound, white, out, own, brightest):
    """Each cell's C_c (3, Hc, Wc) from the smoothed sums (``numerator`` / ``denominator``) and
    the cells' statistics (:func:`_cell_stats`): the censoring and highlight rules (module
    docstring); ``own``: the same from each cell's own readings alone (``weighted`` / ``kept``).
    Cell row by cell row, both while the row's statistics are in cache. ``brightest``: (Wc,) scratch."""
    for i in range(out.shape[1]):
        _cell_values_row(numerator, denominator, mean, info, bound, white, out, brightest, i)
        _cell_values_row(weighted, kept, mean, info, bound, white, own, brightest, i)


@kernel
def _cell_values_row(numerator, denominator, mean, info, bound, white, out, brightest, i):
    """:func:`_cell_values` of cell row ``i`` into ``out``. Loops over the cells of the row (which vectorise)."""
    zero, one, none = np.float32(0.0), np.float32(1.0), np.float32(-1.0)
    # brightest: max over the measured channels of C / white (-1: none measured)
    brightest[:] = none
    for c in range(3):
        num, den, m, n, b, o = numerator[c, i], denominator[c, i], mean[c, i], info[c, i], bound[c, i], out[c, i]
        inverse = one / white[c]
        for j in range(o.size):
            smoothed = num[j] / den[j] if den[j] > zero else zero
            # censored readings: the uncensored neighbours are the darker ones (and those
            # consistent with the bound the brighter): the cell's own readings alone
            value = max(m[j], b[j]) if b[j] > zero else smoothed
            o[j] = max(value, zero)
            # measured: an uncensored reading in the cell, or (a cell at the frame's edge
            # without the channel's pixels) none censored and some around
            measured = n[j] > zero or (b[j] <= zero and den[j] > zero)
            brightest[j] = max(brightest[j], o[j] * inverse if measured else none)
    for c in range(3):  # clipped channels at least the white-balanced level of the measured ones
        n, b, den, o, level = info[c, i], bound[c, i], denominator[c, i], out[c, i], white[c]
        for j in range(o.size):
            measured = n[j] > zero or (b[j] <= zero and den[j] > zero)
            o[j] = o[j] if measured else max(o[j], level * brightest[j])
    for j in range(out.shape[2]):
        if brightest[j] < zero:  # every channel only a bound: neutral white at the largest
            top = max(out[0, i, j] / white[0], max(out[1, i, j] / white[1], out[2, i, j] / white[2]))
            for c in range(3):
                out[c, i, j] = white[c] * top


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


# ----- from cells to pixels ---------------------------------------------------------------

@dataclass(frozen=True)
class Interpolation:
    """A chroma's shares interpolated bilinearly from the cells' centres: along rows to every
    column, and for each frame row the two cell rows around it.

    Attributes:
        rows: float32 (P, Hc, W), on the cell rows at every column: k_R, k_G, k_B, then (with the
            coarse luminance) L and its variance.
        top: intp (H,), the cell row at or above each frame row, clamped.
        frac: float32 (H,), the weight of the cell row below (``top`` + 1), 0 at the edges.
    """

    rows: np.ndarray
    top: np.ndarray
    frac: np.ndarray


def interpolation(ch: Chroma, coarse: bool = False) -> Interpolation:
    """The :class:`Interpolation` of a chroma's shares and, with ``coarse``, its coarse luminance."""
    planes = (ch.shares, ch.coarse) if coarse else (ch.shares,)
    return Interpolation(_full_width(planes, ch.layout.cell[1], ch.shape[1]),
                         *_row_tables(ch.shape[0], ch.shares.shape[1], ch.layout.cell[0]))


def _full_width(planes: tuple[np.ndarray, ...], cx: int, w: int) -> np.ndarray:
    """Cell planes (P, Hc, Wc), given as stacks of them that add up to P, interpolated bilinearly
    along rows from the cells' centres to every column, float32 (P, Hc, W): as OpenCV's linear
    resize (which puts cell j at column j cx + (cx - 1) / 2)."""
    hc, wc = planes[0].shape[1:]
    p = sum(stack.shape[0] for stack in planes)
    if cx in (2, 4):  # OpenCV's own arithmetic, in one pass without its row buffers, and no stacking copy
        rows = np.empty((p, hc, wc * cx), np.float32)
        first = 0
        for stack in planes:
            last = first + stack.shape[0]
            _widen(np.ascontiguousarray(stack).reshape(-1, wc), cx, rows[first:last].reshape(-1, wc * cx))
            first = last
    else:
        stacked = np.ascontiguousarray(np.concatenate(planes) if len(planes) > 1 else planes[0])
        rows = cv2.resize(stacked.reshape(p * hc, wc), (wc * cx, p * hc),
                          interpolation=cv2.INTER_LINEAR).reshape(p, hc, wc * cx)
    return rows[:, :, :w]


@intrinsic
def _fma(typingctx, a, b, c):
    """a b + c rounded once (float32), as OpenCV's linear resize computes its taps."""
    def codegen(context, builder, signature, args):
        return builder.fma(*args)
    return types.float32(types.float32, types.float32, types.float32), codegen


@kernel
def _widen(planes, cx, out):
    """out (N, cx Wc) = ``planes`` (N, Wc) float32 interpolated linearly along rows, cell j at column
    j cx + (cx - 1) / 2, the ends held (cx 2 or 4): bit for bit OpenCV's INTER_LINEAR resize, each
    value a + (b - a) f with one rounding of the product and sum, f = (k + 1/2) / cx."""
    wc = planes.shape[1]
    c0 = cx // 2  # the first column past cell 0's centre
    for i in range(planes.shape[0]):
        p, o = planes[i], out[i]
        for x in range(c0):
            o[x] = p[0]
        if cx == 2:
            q, t = np.float32(0.25), np.float32(0.75)
            for j in range(wc - 1):
                a = p[j]
                d = p[j + 1] - a
                o[2 * j + 1] = _fma(d, q, a)
                o[2 * j + 2] = _fma(d, t, a)
        else:
            f0, f1, f2, f3 = np.float32(0.125), np.float32(0.375), np.float32(0.625), np.float32(0.875)
            for j in range(wc - 1):
                a = p[j]
                d = p[j + 1] - a
                o[4 * j + 2] = _fma(d, f0, a)
                o[4 * j + 3] = _fma(d, f1, a)
                o[4 * j + 4] = _fma(d, f2, a)
                o[4 * j + 5] = _fma(d, f3, a)
        for x in range(cx * (wc - 1) + c0, o.size):
            o[x] = p[wc - 1]


@lru_cache(maxsize=16)
def _row_tables(h: int, hc: int, cy: int) -> tuple[np.ndarray, np.ndarray]:
    """(top, frac) of :class:`Interpolation` for frames of ``h`` rows, cells of ``cy`` rows, read-only."""
    u = (np.arange(h) - (cy - 1) / 2) / cy
    top = np.floor(u)
    frac = (u - top).astype(np.float32)
    frac[(top < 0) | (top >= hc - 1)] = 0
    top = np.clip(top, 0, hc - 1).astype(np.intp)
    for array in (top, frac):
        array.setflags(write=False)
    return top, frac


#: Rows per piece of the per-pixel passes when they are spread over threads.
PIECE_ROWS = 128


def _pieces(h: int, align: int = 1) -> list[slice]:
    """Row ranges of about PIECE_ROWS rows (multiples of ``align``) covering ``h`` rows."""
    step = max(PIECE_ROWS // align, 1) * align
    return [slice(r, min(r + step, h)) for r in range(0, h, step)]


def folded_exposure(inp: SveInput, inter: Interpolation, workers: int | Executor = 1,
                    inverse: np.ndarray | None = None) -> np.ndarray:
    """e' = e k_c of every pixel, float32 (H, W) (module docstring, step b); ``workers``: base.map_on.
    With ``inverse`` (float32 (H, W)), 1 / e' is written there in the same pass."""
    out = np.empty(inp.shape, np.float32)
    channel_rows = _channel_rows(inp.cfa, inp.shape[1])
    none = np.empty((0, 0), np.float32)

    def piece(rows: slice) -> None:
        _fold(inp.exposure[rows], channel_rows, rows.start, inter.rows, inter.top[rows], inter.frac[rows], out[rows],
              none if inverse is None else inverse[rows])

    map_on(workers, piece, _pieces(inp.shape[0]))
    return out


@lru_cache(maxsize=16)
def _channel_rows(cfa: ColourFilter, width: int) -> np.ndarray:
    """The channel of every pixel of the CFA tile's rows, uint8 (th, width), read-only."""
    rows = cfa.channel_map((cfa.shape[0], width))
    rows.setflags(write=False)
    return rows


def colourise(luminance: np.ndarray, inter: Interpolation, workers: int | Executor = 1) -> np.ndarray:
    """RGB = Y k_c, float32 (H, W, 3), from the luminance Y (H, W) (module docstring, step c)."""
    out = np.empty((*luminance.shape, 3), np.float32)
    luminance = np.ascontiguousarray(luminance, np.float32)

    interleaved = out.reshape(luminance.shape[0], -1)  # (H, 3 W): the kernel's stores, one flat row each

    def piece(rows: slice) -> None:
        _colourise(luminance[rows], inter.rows, inter.top[rows], inter.frac[rows], interleaved[rows])

    map_on(workers, piece, _pieces(luminance.shape[0]))
    return out


@kernel
def _fold(exposure, channel_rows, first, rows, top, frac, out, inverse):
    """out = e k_c of each pixel's channel c (``channel_rows``: the CFA's rows; the arrays' row r is
    frame row ``first`` + r), k_c interpolated between the pixel's two cell rows: the two values of
    its channel chosen first (every value loaded before the choice, which vectorises), then one
    interpolation per pixel (not three into a scratch row, then the choice: 25 % faster).
    ``inverse``: 1 / out where it is not empty."""
    period, last = channel_rows.shape[0], rows.shape[1] - 1
    for r in range(exposure.shape[0]):
        t0, f = top[r], frac[r]
        t1 = min(t0 + 1, last)
        a0, b0, a1, b1, a2, b2 = rows[0, t0], rows[0, t1], rows[1, t0], rows[1, t1], rows[2, t0], rows[2, t1]
        ch, e, o = channel_rows[(first + r) % period], exposure[r], out[r]
        for x in range(o.size):
            c, p0, p1, p2, q0, q1, q2 = ch[x], a0[x], a1[x], a2[x], b0[x], b1[x], b2[x]
            a = p0 if c == 0 else (p1 if c == 1 else p2)
            b = q0 if c == 0 else (q1 if c == 1 else q2)
            o[x] = e[x] * (a + (b - a) * f)
        if inverse.size > 0:
            v, one = inverse[r], np.float32(1.0)
            for x in range(o.size):
                v[x] = one / o[x]


@kernel
def _colourise(luminance, rows, top, frac, out):
    """out (H, 3 W), the rows of (H, W, 3) = Y k_c, the shares interpolated between each row's two
    cell rows in the loop. Stores into flat rows: into (H, W, 3) the loop does not vectorise (25 %
    slower)."""
    last = rows.shape[1] - 1
    for r in range(luminance.shape[0]):
        t0, f = top[r], frac[r]
        t1 = min(t0 + 1, last)
        a0, b0, a1, b1, a2, b2 = rows[0, t0], rows[0, t1], rows[1, t0], rows[1, t1], rows[2, t0], rows[2, t1]
        y, o = luminance[r], out[r]
        for x in range(y.size):
            v = y[x]
            o[3 * x] = v * (a0[x] + (b0[x] - a0[x]) * f)
            o[3 * x + 1] = v * (a1[x] + (b1[x] - a1[x]) * f)
            o[3 * x + 2] = v * (a2[x] + (b2[x] - a2[x]) * f)


# ----- joint ----------------------------------------------------------------------------------

@dataclass(frozen=True)
class Joint:
    """The joint reconstruction and its parts (a stream fuses them).

    Attributes:
        estimate: the colour Estimate (see :func:`run_colour`).
        luminance_input: the monochrome SVE frame of the luminance (exposures e', SveInput.folded;
            or, for a method that reads only the tile, readings divided by k_c).
        chroma: the frame's chroma.
        interpolation: its interpolation (shares, and the coarse luminance after them when the
            luminance was refined).
        inverse_exposure: float32 (H, W), 1 / e' of ``luminance_input`` where it was asked for
            with folded exposures (a stream's fusion reads it), else None.
    """

    estimate: Estimate
    luminance_input: SveInput
    chroma: Chroma
    interpolation: Interpolation
    inverse_exposure: np.ndarray | None = None


def luminance_input(inp: SveInput, inter: Interpolation, exposures: bool = True,
                    workers: int | Executor = 1, inverse: np.ndarray | None = None) -> SveInput:
    """The monochrome SVE frame of the luminance: exposures e' (``exposures``, folded) or, for a
    method that reads only the pattern's tile, readings s e / e' with the nominal exposures.
    ``inverse`` (float32 (H, W)): where 1 / e' is written, with the folding (folded_exposure)."""
    folded = folded_exposure(inp, inter, workers, inverse)
    if exposures:  # a calibrated map is in e' already: the nominal tile keeps the method's strips
        pattern = inp.pattern if inp.pattern.pixel_map is None else Pattern(inp.pattern.tile)
        return SveInput(inp.signal, folded, inp.censored, pattern, inp.sensor, inp.integral, folded=True)
    signal = inp.signal * inp.exposure
    signal /= folded
    return SveInput(signal, inp.exposure, inp.censored, inp.pattern, inp.sensor, False)


def joint(inp: SveInput, spec: MethodSpec, rgb: bool = True, refined: bool = True, inverse_exposure: bool = False,
          **options) -> Joint:
    """The joint reconstruction (module docstring) with the mono method ``spec`` and its ``options``.

    With a method that reports its variance and ``refined``, the luminance is refined at the
    chroma's scale (:func:`refine`); the estimate's variance is then the refined one's.
    ``rgb`` False leaves the colour out (the estimate's image is then the luminance). A stream
    takes neither: it fuses the frames' luminance and chroma, then refines and colours.
    ``inverse_exposure``: also 1 / e' (Joint.inverse_exposure), made while e' is (a method that
    reads per-pixel exposures only).
    """
    workers = options.get("workers", 1)  # the method's threads serve the colour passes too
    ch = chroma(inp)
    inter = interpolation(ch, coarse=spec.variance and refined)
    inverse = np.empty(inp.shape, np.float32) if inverse_exposure and spec.exposures else None
    lum = luminance_input(inp, inter, spec.exposures, workers, inverse)
    if spec.variance:
        options = {**options, "return_variance": True}
    est = spec.run(lum, **options)
    luminance, variance = est.image, est.variance
    if variance is not None and refined:
        refined_variance = np.empty_like(variance)
        luminance = refine(luminance, variance, inter, ch.layout.cell, out_variance=refined_variance,
                           new_variance=True, workers=workers)
        variance = refined_variance
    image = colourise(luminance, inter, workers) if rgb else luminance
    return Joint(Estimate(image, est.lower_bound, variance, luminance, window=est.window), lum, ch, inter, inverse)


def refine(luminance: np.ndarray, variance: np.ndarray, inter: Interpolation, cell: tuple[int, int], *,
           weight: np.ndarray | None = None, out: np.ndarray | None = None,
           out_variance: np.ndarray | None = None, new_variance: bool = False,
           workers: int | Executor = 1) -> np.ndarray:
    """Move the luminance Y towards the coarse L where they differ by no more than noise.

    Y (the mono method's, variance v_Y) and L (the chroma cells', variance v_L; module
    docstring) estimate the same luminance; L is far less noisy but blurred. L uses the
    readings Y uses, with lower weights, so Y - L has variance v_Y - v_L plus the squared bias
    b^2 of L (for nested inverse-variance estimates the covariance is v_L). Its MMSE
    combination is L + beta (Y - L), beta = b^2 / (b^2 + v_Y - v_L), with b^2 estimated from
    the local mean E of (Y - L)^2 over each cell: beta = max(0, 1 - (v_Y - v_L) / E), a
    positive-part James-Stein garrote (as svelive.reconstruction.fusion.sharpen). Where the
    scene has structure finer than the chroma's, E exceeds the noise and Y stays; in flat
    regions in the read-noise regime, where Y is mostly noise, the result is L. Not near
    censored readings (v_L is COARSE_NONE there), nor where v_L >= v_Y. The variance
    becomes v_L + beta (v_Y - v_L).

    Args:
        luminance, variance: float32 (H, W), Y and v_Y (not modified unless they are ``out``
            or ``out_variance``).
        inter: the chroma's interpolation with its coarse planes.
        cell: the cells' (rows, cols).
        weight: float32 (H, W) or None: v_Y is ``variance`` times it (a stream's history weight).
        out, out_variance: where to write the result and its variance (a new array, and not
            computed, when None).
        new_variance: ``out_variance`` is none of the inputs (with ``out`` None, both are
            written in one loop that vectorises, without a scratch row).
        workers: threads for its pieces of rows (base.map_on); the result does not depend on it.

    Returns:
        ``out``, float32 (H, W).
    """
    (cy, cx), (h, w) = cell, luminance.shape
    hc, wc = inter.rows.shape[1], -(-w // cx)
    residual = np.empty((1, hc, wc), np.float32)

    def cells(rows: slice) -> None:  # whole cells: pieces aligned on the cells' rows
        _residual_cells(luminance[rows], inter.rows[3], inter.top[rows], inter.frac[rows], cy, cx,
                        residual[0, rows.start // cy:-(-rows.stop // cy)], np.empty((2, w), np.float32))

    map_on(workers, cells, _pieces(h, cy))
    residual_rows = _full_width((residual,), cx, w)[0]
    none = np.empty((0, 0), np.float32)
    if out is None and (out_variance is None or new_variance):  # written in the loop (no scratch row: 40 % faster)
        out = np.empty((h, w), np.float32)

        def fresh(rows: slice) -> None:
            _refine_into(luminance[rows], variance[rows], none if weight is None else weight[rows], inter.rows[3],
                         inter.rows[4], residual_rows, inter.top[rows], inter.frac[rows], out[rows],
                         none if out_variance is None else out_variance[rows])

        map_on(workers, fresh, _pieces(h))
        return out
    out = np.empty((h, w), np.float32) if out is None else out

    def piece(rows: slice) -> None:
        _refine(luminance[rows], variance[rows], none if weight is None else weight[rows], inter.rows[3],
                inter.rows[4], residual_rows, inter.top[rows], inter.frac[rows], out[rows],
                none if out_variance is None else out_variance[rows], np.empty((2, w), np.float32))

    map_on(workers, piece, _pieces(h))
    return out


@kernel
def _residual_cells(luminance, coarse, top, frac, cy, cx, out, row):
    """out (Hc, Wc) = the mean over each cell of (Y - L)^2, L the coarse luminance; ``row`` (2, W) scratch:
    its second row holds (Y - L)^2 added up over the cell's rows before the cells' columns are."""
    h, w = luminance.shape
    total = row[1]
    zero = np.float32(0.0)
    last = coarse.shape[0] - 1
    for i in range(out.shape[0]):
        r0, r1 = i * cy, min(i * cy + cy, h)
        total[:] = zero
        for r in range(r0, r1):
            t, f = top[r], frac[r]
            a, b, y = coarse[t], coarse[min(t + 1, last)], luminance[r]
            for x in range(w):  # L interpolated in the loop (through a scratch row: 30 % slower)
                d = y[x] - (a[x] + (b[x] - a[x]) * f)
                total[x] += d * d
        o, start = out[i], 0
        if cx == 2:  # cells of two columns spelt out: a loop that vectorises (the same sums)
            start, count = w // 2, np.float32((r1 - r0) * 2)
            for j in range(start):
                o[j] = (zero + total[2 * j] + total[2 * j + 1]) / count
        for j in range(start, o.size):
            x0, x1 = j * cx, min(j * cx + cx, w)
            s = zero
            for x in range(x0, x1):
                s += total[x]
            o[j] = s / np.float32((r1 - r0) * (x1 - x0))


@kernel
def _garrote(y, v, l0, l1, v0, v1, e0, e1, f):
    """One pixel of :func:`refine`'s garrote: its luminance ``y`` of variance ``v`` against the coarse
    luminance, its variance and the residual power interpolated between two rows (l0, l1; v0, v1;
    e0, e1) at ``f``; returns (refined value, its variance). Inlined into the row loops below.

    With t = max(v_Y - v_L, 0), beta = max(1 - t / E, 0) is 1 where t is 0; the variance is
    v_L + beta t (v_L where beta is 0, also for an infinite v_Y) where t > 0, v_Y elsewhere."""
    zero, one, tiny = np.float32(0.0), np.float32(1.0), np.float32(1e-30)
    lum = l0 + (l1 - l0) * f
    var = v0 + (v1 - v0) * f
    res = e0 + (e1 - e0) * f
    t = max(v - var, zero)  # v_Y - v_L: the noise of Y - L
    beta = max(one - t / max(res, tiny), zero)
    return lum + (y - lum) * beta, (v if t <= zero else (var if beta <= zero else var + beta * t))


@kernel
def _refine(luminance, variance, weight, coarse, coarse_variance, residual, top, frac, out, out_variance, rows):
    """The garrote of :func:`refine` per pixel; ``weight`` and ``out_variance`` may be empty (none).
    ``out`` and ``out_variance`` may be ``luminance`` and ``variance``: each row is computed into
    ``rows`` (2, W) first, so that the loop (the coarse planes interpolated in it) vectorises
    (:func:`_refine_into` stores in the loop; called per row from here it measured 7-13 % slower)."""
    weighted, with_variance = weight.size > 0, out_variance.size > 0
    last = coarse.shape[0] - 1
    for r in range(luminance.shape[0]):
        t0, f = top[r], frac[r]
        t1 = min(t0 + 1, last)
        l0, l1, v0, v1, e0, e1 = (coarse[t0], coarse[t1], coarse_variance[t0], coarse_variance[t1],
                                  residual[t0], residual[t1])
        y, vy, o, ov = luminance[r], variance[r], rows[0], rows[1]
        wy = weight[r] if weighted else vy  # (not read without a weight)
        for x in range(y.size):
            o[x], ov[x] = _garrote(y[x], vy[x] * wy[x] if weighted else vy[x], l0[x], l1[x], v0[x], v1[x],
                                   e0[x], e1[x], f)
        out[r] = o
        if with_variance:
            out_variance[r] = ov


@kernel
def _refine_into(luminance, variance, weight, coarse, coarse_variance, residual, top, frac, out, out_variance):
    """:func:`_refine` into ``out`` and ``out_variance`` (may be empty) that are none of the inputs:
    the same arithmetic per pixel, stored in the loop."""
    weighted, with_variance = weight.size > 0, out_variance.size > 0
    last = coarse.shape[0] - 1
    for r in range(luminance.shape[0]):
        t0, f = top[r], frac[r]
        t1 = min(t0 + 1, last)
        l0, l1, v0, v1, e0, e1 = (coarse[t0], coarse[t1], coarse_variance[t0], coarse_variance[t1],
                                  residual[t0], residual[t1])
        y, vy, o = luminance[r], variance[r], out[r]
        wy = weight[r] if weighted else vy  # (not read without a weight)
        for x in range(y.size):
            o[x], ov = _garrote(y[x], vy[x] * wy[x] if weighted else vy[x], l0[x], l1[x], v0[x], v1[x],
                                e0[x], e1[x], f)
            if with_variance:
                out_variance[r, x] = ov


# ----- split (the baseline) -----------------------------------------------------------------

def split(inp: SveInput, spec: MethodSpec, **options) -> Estimate:
    """The baseline (module docstring): the mono method per CFA-phase sub-image, then demosaicing."""
    cfa, pattern = inp.cfa, inp.pattern
    reduced = cfa.block_tile()
    mosaic, variance = np.empty(inp.shape, np.float32), np.empty(inp.shape, np.float32)
    lower = np.empty(inp.shape, bool)
    for qy in range(reduced.shape[0]):
        for qx in range(reduced.shape[1]):
            rows, cols, sub_pattern = colour_phase(pattern, cfa, inp.shape, (qy, qx))
            if rows.size == 0 or cols.size == 0:
                continue
            where = np.ix_(rows, cols)
            sub = SveInput(np.ascontiguousarray(inp.signal[where]), exposure_maps(sub_pattern, (rows.size, cols.size))[0],
                           np.ascontiguousarray(inp.censored[where]), sub_pattern, inp.sensor, inp.integral)
            est = spec.run(sub, **options)
            mosaic[where] = est.image
            lower[where] = est.lower_bound
            variance[where] = np.inf if est.variance is None else est.variance
    floor = float(np.sqrt(inp.sensor.floor_variance) / pattern.tile.max())  # noise floor of the longest exposure
    image = demosaic(mosaic, cfa, floor)
    share = cell_layout(pattern, cfa).share
    luminance = np.ascontiguousarray(image @ share)
    has_variance = bool(np.all(np.isfinite(variance[:1])))
    lum_variance = _interpolated_variance(variance, cfa, share) if has_variance else None
    lum_lower = _spread(lower, cfa)
    return Estimate(image, lum_lower, lum_variance, luminance)


def demosaic(mosaic: np.ndarray, cfa: ColourFilter, floor: float) -> np.ndarray:
    """RGB (H, W, 3) float32 from an HDR mosaic (H, W) (>= 0, DN), interpolated in log2(x + floor)
    encoded to 16 bits: OpenCV's edge-aware Bayer demosaicing, or a tent normalised convolution."""
    log = np.log2(np.maximum(mosaic, 0) + np.float32(floor))
    low, high = float(log.min()), float(log.max())
    step = max(high - low, 1e-6) / 65535.0
    if cfa.is_bayer() and min(mosaic.shape) >= 2:
        code = np.rint((log - low) / step).astype(np.uint16)
        rgb_code = cv2.demosaicing(code, getattr(cv2, f"COLOR_Bayer{cfa.name}2RGB_EA")).astype(np.float32)
    else:
        rgb_code = np.stack([_tent_interpolation(np.rint((log - low) / step).astype(np.float32), cfa, c)
                             for c in range(3)], axis=-1)
    rgb = np.exp2(rgb_code * np.float32(step) + np.float32(low)) - np.float32(floor)
    return np.maximum(rgb, 0, out=rgb).astype(np.float32, copy=False)


def _tent(length: int) -> np.ndarray:
    """Separable tent reaching ``length`` - 1 pixels each side, float32 (2 length - 1,)."""
    return np.concatenate([np.arange(1, length + 1), np.arange(length - 1, 0, -1)]).astype(np.float32)


def _tent_interpolation(values: np.ndarray, cfa: ColourFilter, channel: int) -> np.ndarray:
    """Channel ``channel`` of a mosaic at every pixel: its own value where the CFA has it, else
    the tent-weighted mean of its samples around (normalised convolution), float32 (H, W)."""
    mask = (cfa.channel_map(values.shape) == channel).astype(np.float32)
    ky, kx = _tent(cfa.shape[0]), _tent(cfa.shape[1])
    num, den = smooth(values * mask, ky, kx), smooth(mask, ky, kx)
    out = np.divide(num, den, out=np.zeros_like(num), where=den > 0)
    np.copyto(out, values, where=mask > 0)
    return out


def _interpolated_variance(variance: np.ndarray, cfa: ColourFilter, share: np.ndarray) -> np.ndarray:
    """Variance of the luminance sum_c n_c C_c, each channel's variance interpolated as its values."""
    out = np.zeros(variance.shape, np.float32)
    for c in range(3):
        out += np.float32(share[c] ** 2) * _tent_interpolation(variance, cfa, c)
    return out


def _spread(lower: np.ndarray, cfa: ColourFilter) -> np.ndarray:
    """Pixels whose interpolation reads a lower bound: ``lower`` dilated over the CFA's period."""
    if not lower.any():
        return lower
    size = (2 * cfa.shape[1] - 1, 2 * cfa.shape[0] - 1)
    return cv2.dilate(lower.view(np.uint8), np.ones(size[::-1], np.uint8)).view(bool)
