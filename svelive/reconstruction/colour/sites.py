"""Chroma per site (svelive.reconstruction.colour, step c'): on a 2x2 Bayer CFA, each pixel's colour
ratios R/G and B/G estimated from its own 3x3 neighbourhood along rows and along columns, weighed by
the noise model and by how much the luminance varies along each direction, and taken instead of the
cells' ratios by a noise-model garrote where the local evidence shows them different beyond that
expected error (:func:`site_chroma`).

The cells (step a) hold a chroma of 4x2 pixels (dual-ISO): a light seen by a few sites of each colour,
a thin coloured line, colour texture come out with the cells' colour. At each pixel (r, c) the 3x3
neighbourhood pairs every channel with green twice, along both directions:

- rows: the pixel's own row gives log(X / G) of its non-green channel X (the centre reading against
  the mean of its two horizontal neighbours, or those against it at a green site); rows r - 1 and
  r + 1 give the other channel's ratio the same way (inverse-variance combined);
- columns: the same with columns c, c - 1 and c + 1.

Each ratio's two means share their centroid (the centre column or row), and every reading of the
3x3 lies inside a light of 3x3 pixels centred there. Its variance is the delta method's,
v_X / m_X^2 + v_G / m_G^2, with each reading's variance from the noise model at its own exposure
((e m / g + sigma^2) / e^2, the mean m of its pair as the pilot), so the short rows of dual-ISO weigh
less than the long ones. A direction that crosses an edge aliases (its two means read different
sides): the expected squared error of a direction is its variance plus the luminance's mean squared
log step along it over the 3x3 (the log of the luminance Y of step b, floored at the longest
exposure's read noise), and the two directions are combined by the inverse of those, which is also
the estimate's expected squared error t. Any censored reading in a direction's 3x3 leaves that
direction out (a censored reading is only a bound), and a censored pixel keeps the cells' chroma, as
do the frame's outer pixels: clipped highlights stay as the cells' rules make them (no magenta).

The choice, per pixel and per ratio: the residual d = rho_site - rho_cells is averaged over the 3x3
pixels with weights 1 / t (its variance 81/25 over the weights' sum: the 3x3 estimates' footprints
cover 5x5 readings), and rho = rho_cells + beta d, beta = max(0, 1 - v / E), with E the mean of d^2
over 5x5 pixels (the garrote of steps a and b'): where the per-site ratios are noisy (dim regions,
short-exposure sites) or alias, v is at least E and the cells' chroma stays; where the data shows
colour finer than the cells beyond v (bright sites, small lights, colour edges along one
direction), the per-site ratios are taken. Each pixel keeps its own channel's value (Y k_c) and the
other two channels become it times the chosen ratios; the luminance becomes sum_c n_c RGB_c where a
pixel changed.

Opt-in (``joint(..., site_chroma=True)``, default off): docs/peers.md has its measurements (bright
frames gain, dim ones lose up to 0.3 dB: the 5x5 evidence holds few independent residuals, so
noise passes the garrote at a fraction of the pixels; and it costs about 150-220 ms at 1920x1200).
"""

from __future__ import annotations

from concurrent.futures import Executor

import cv2
import numpy as np

from svelive.core.cfa import ColourFilter
from svelive.jit import kernel
from svelive.reconstruction.colour.interpolate import _pieces
from svelive.reconstruction.methods.base import SveInput, map_on

#: A variance standing for "no estimate" (finite, as COARSE_NONE).
_NONE = np.float32(1e30)
#: The smoothed residuals' variance over the inverse of their weights' sum: the 3x3 estimates' own 3x3
#: footprints cover 5x5 readings, so nine of them hold about as much as 25 / 9 independent ones.
_OVERLAP = np.float32(81.0 / 25.0)
#: The evidence window (pixels): it holds about (5 / 3)^2 independent smoothed residuals.
EVIDENCE = 5


def applies(cfa: ColourFilter | None) -> bool:
    """Whether chroma per site applies to ``cfa``: a 2x2 Bayer tile (green on one diagonal)."""
    if cfa is None or cfa.tile.shape != (2, 2):
        return False
    t = cfa.tile
    return bool((t[0, 0] == 1 and t[1, 1] == 1 and {int(t[0, 1]), int(t[1, 0])} == {0, 2})
                or (t[0, 1] == 1 and t[1, 0] == 1 and {int(t[0, 0]), int(t[1, 1])} == {0, 2}))


def site_chroma(inp: SveInput, luminance: np.ndarray, rgb: np.ndarray, share: np.ndarray,
                workers: int | Executor = 1) -> bool:
    """Chroma per site (module docstring) into ``rgb`` (float32 (H, W, 3), Y k_c) and ``luminance``
    (float32 (H, W), Y), in place. ``share``: n_c of the CFA. Returns False (nothing done) where it
    does not apply (not a 2x2 Bayer CFA, a frame under 3x3)."""
    h, w = inp.shape
    if not applies(inp.cfa) or h < 3 or w < 3 or inp.channels is None:
        return False
    f32 = np.float32
    sensor = inp.sensor
    floor = f32(np.sqrt(sensor.floor_variance) / float(np.max(inp.exposure)))
    gain_inv, floor_var = f32(1.0 / sensor.effective_gain), f32(sensor.floor_variance)
    signal, exposure = np.ascontiguousarray(inp.signal, f32), np.ascontiguousarray(inp.exposure, f32)
    log_y, ratios = np.empty((h, w), f32), np.empty((4, h, w), f32)
    weighted, smoothed = np.empty((4, h, w), f32), np.empty((4, h, w), f32)
    chosen, evidence = np.empty((6, h, w), f32), np.empty((2, h, w), f32)

    def lines(rows: slice) -> None:
        _line_ratios(signal, exposure, inp.censored, inp.channels, rgb, luminance, floor, gain_inv, floor_var,
                     rows.start, rows.stop, log_y, ratios, np.empty((3, w), f32))

    def estimates(rows: slice) -> None:
        _site_ratios(ratios, log_y, inp.censored, inp.channels, rgb, rows.start, rows.stop, weighted)

    def residuals(rows: slice) -> None:
        _residuals(weighted[:, rows], smoothed[:, rows], chosen[:, rows])

    def choose(rows: slice) -> None:
        _choose(chosen[:, rows], evidence[:, rows], inp.channels[rows], np.asarray(share, f32), rgb[rows],
                luminance[rows])

    map_on(workers, lines, _pieces(h))
    map_on(workers, estimates, _pieces(h))
    for k in range(4):  # the residuals' inverse-t weighted 3x3 sums
        cv2.blur(weighted[k], (3, 3), dst=smoothed[k], borderType=cv2.BORDER_REFLECT_101)
    map_on(workers, residuals, _pieces(h))
    for k in range(2):  # the evidence: the smoothed residuals' mean square over EVIDENCE x EVIDENCE pixels
        cv2.blur(chosen[2 + k], (EVIDENCE, EVIDENCE), dst=evidence[k], borderType=cv2.BORDER_REFLECT_101)
    map_on(workers, choose, _pieces(h))
    return True


@kernel
def _line_ratios(signal, exposure, censored, channels, rgb, luminance, floor, gain_inv, floor_var, first, last,
                 log_y, out, pilot):
    """For rows ``first`` to ``last``: ``log_y`` = log(max(Y, floor)), and ``out`` (4, H, W): the row
    ratio at each pixel (0: log(X / G) of the centre reading against the mean of its two horizontal
    neighbours, X the non-green one of the two channels; 1: its variance, _NONE where a reading is
    censored, a mean is not positive, or at the frame's left and right edge), and the column ratio
    likewise (2, 3; vertical neighbours, top and bottom edge). Each reading's pilot is its own
    channel in ``rgb`` (the cells' estimate there); ``pilot``: (3, W) scratch."""
    h, w = signal.shape
    zero, none = np.float32(0.0), _NONE
    for r in range(first, last):
        y, ly = luminance[r], log_y[r]
        for x in range(w):
            ly[x] = np.log(max(y[x], floor))
        s, e, lost, ch, p = signal[r], exposure[r], censored[r], channels[r], pilot[1]
        _pilots(rgb, channels, r, pilot[1])
        hr, hv, vr, vv = out[0, r], out[1, r], out[2, r], out[3, r]
        hr[0], hv[0], hr[w - 1], hv[w - 1] = zero, none, zero, none
        for x in range(1, w - 1):
            hr[x], hv[x] = _pair(s[x], e[x], lost[x], ch[x], p[x], s[x - 1], e[x - 1], lost[x - 1], p[x - 1],
                                 s[x + 1], e[x + 1], lost[x + 1], p[x + 1], gain_inv, floor_var)
        if r == 0 or r == h - 1:
            for x in range(w):
                vr[x], vv[x] = zero, none
            continue
        s0, e0, l0, p0 = signal[r - 1], exposure[r - 1], censored[r - 1], pilot[0]
        s1, e1, l1, p1 = signal[r + 1], exposure[r + 1], censored[r + 1], pilot[2]
        _pilots(rgb, channels, r - 1, p0)
        _pilots(rgb, channels, r + 1, p1)
        for x in range(w):
            vr[x], vv[x] = _pair(s[x], e[x], lost[x], ch[x], p[x], s0[x], e0[x], l0[x], p0[x], s1[x], e1[x], l1[x],
                                 p1[x], gain_inv, floor_var)


@kernel
def _pilots(rgb, channels, r, out):
    """out (W,) = each pixel's own channel of ``rgb`` on row ``r``."""
    ch = channels[r]
    for x in range(out.size):
        out[x] = rgb[r, x, ch[x]]


@kernel
def _pair(sc, ec, lc, cc, pc, sa, ea, la, pa, sb, eb, lb, pb, gain_inv, floor_var):
    """log(X / G) of a centre reading (signal ``sc``, exposure ``ec``, censored ``lc``, channel ``cc``)
    against the mean of its two neighbours a and b (the other channel), and its variance by the
    delta method, each reading's noise-model variance at its exposure and at its pilot (``pc``,
    ``pa``, ``pb``: the cells' estimate of its channel there, not the reading itself, whose noise
    would make a low reading look precise); (0, _NONE) where a reading is censored or a mean or a
    pilot is not positive."""
    zero, half = np.float32(0.0), np.float32(0.5)
    if lc or la or lb:
        return zero, _NONE
    xc = sc / ec
    side = half * (sa / ea + sb / eb)
    pside = half * (pa + pb)
    if xc <= zero or side <= zero or pc <= zero or pside <= zero:
        return zero, _NONE
    vc = (ec * pc * gain_inv + floor_var) / (ec * ec)
    va = (ea * pa * gain_inv + floor_var) / (ea * ea)
    vb = (eb * pb * gain_inv + floor_var) / (eb * eb)
    mc, ms = min(xc, pc), min(side, pside)  # the log's slope at the smaller: a reading far below its pilot is
    v = vc / (mc * mc) + np.float32(0.25) * (va + vb) / (ms * ms)  # noise or structure, either way uncertain
    ratio = np.log(xc / side)
    return (-ratio if cc == 1 else ratio), min(v, _NONE)


@kernel
def _combine(r0, v0, r1, v1):
    """Inverse-variance mean of two estimates and its variance (_NONE: none)."""
    if v0 >= _NONE:
        return r1, v1
    if v1 >= _NONE:
        return r0, v0
    w0, w1 = np.float32(1.0) / v0, np.float32(1.0) / v1
    total = w0 + w1
    return (w0 * r0 + w1 * r1) / total, np.float32(1.0) / total


@kernel
def _site_ratios(ratios, log_y, censored, channels, rgb, first, last, out):
    """Per pixel of rows ``first`` to ``last``: the per-site log(R / G) and log(B / G) (rows and
    columns, module docstring), each direction's expected squared error its variance plus the mean
    squared log-luminance step along it over the 3x3, combined (:func:`_directions`) into t; out
    (4, H, W) = (w d, w) of each ratio, d its difference from the cells' ratio (``rgb``) and
    w = 1 / t (0 where it has none: a censored pixel, a channel not positive, the frame's edge)."""
    h, w = log_y.shape
    zero, one, sixth = np.float32(0.0), np.float32(1.0), np.float32(1.0 / 6.0)
    for r in range(first, last):
        wda, wa, wdb, wb = out[0, r], out[1, r], out[2, r], out[3, r]
        for x in range(w):
            wda[x], wa[x], wdb[x], wb[x] = zero, zero, zero, zero
        if r == 0 or r == h - 1:
            continue
        lu, lm, ld = log_y[r - 1], log_y[r], log_y[r + 1]
        ch, lost = channels[r], censored[r]
        for x in range(1, w - 1):
            c = ch[x]
            red, green, blue = rgb[r, x, 0], rgb[r, x, 1], rgb[r, x, 2]
            if lost[x] or red <= zero or green <= zero or blue <= zero:
                continue
            # the luminance's mean squared log step along rows and along columns over the 3x3
            g_h = zero
            g_v = zero
            for row in (lu, lm, ld):
                d0, d1 = row[x] - row[x - 1], row[x + 1] - row[x]
                g_h += d0 * d0 + d1 * d1
            for k in range(x - 1, x + 2):
                d0, d1 = lm[k] - lu[k], ld[k] - lm[k]
                g_v += d0 * d0 + d1 * d1
            g_h *= sixth
            g_v *= sixth
            # rows: the own row's ratio is of the pixel's row's non-green channel; rows above and below the other's
            own_h, own_hv = ratios[0, r, x], ratios[1, r, x]
            other_h, other_hv = _combine(ratios[0, r - 1, x], ratios[1, r - 1, x], ratios[0, r + 1, x],
                                         ratios[1, r + 1, x])
            own_v, own_vv = ratios[2, r, x], ratios[3, r, x]
            other_v, other_vv = _combine(ratios[2, r, x - 1], ratios[3, r, x - 1], ratios[2, r, x + 1],
                                         ratios[3, r, x + 1])
            # which non-green channel the own row (column) holds: the pixel's own, or (green) its neighbour's
            row_red = (c == 0) or (c == 1 and ch[x + 1] == 0)
            col_red = (c == 0) or (c == 1 and channels[r + 1, x] == 0)
            a_h, av_h, b_h, bv_h = (own_h, own_hv, other_h, other_hv) if row_red else (other_h, other_hv, own_h, own_hv)
            a_v, av_v, b_v, bv_v = (own_v, own_vv, other_v, other_vv) if col_red else (other_v, other_vv, own_v, own_vv)
            ra, ta = _directions(a_h, av_h, a_v, av_v, g_h, g_v)
            rb, tb = _directions(b_h, bv_h, b_v, bv_v, g_h, g_v)
            if ta < _NONE:
                wa[x] = one / ta
                wda[x] = wa[x] * (ra - np.log(red / green))
            if tb < _NONE:
                wb[x] = one / tb
                wdb[x] = wb[x] * (rb - np.log(blue / green))


@kernel
def _residuals(weighted, smoothed, out):
    """For a piece of rows: out (6, ...) = the smoothed residuals of log(R / G) and log(B / G) from
    the cells' (the inverse-t weighted 3x3 means, ``smoothed`` the 3x3 sums of ``weighted``), their
    squares (the evidence: also where the pixel has no estimate of its own, but some around), and
    their variances (_OVERLAP over the weights' 3x3 sum; _NONE where the pixel has no estimate of its
    own: it keeps the cells' chroma)."""
    zero = np.float32(0.0)
    nine = np.float32(9.0)
    for k in range(2):
        for r in range(out.shape[1]):
            own, num, den = weighted[2 * k + 1, r], smoothed[2 * k, r], smoothed[2 * k + 1, r]
            res, sq, var = out[k, r], out[2 + k, r], out[4 + k, r]
            for x in range(res.size):
                some = den[x] > zero
                d = num[x] / den[x] if some else zero
                res[x] = d
                sq[x] = d * d
                var[x] = _OVERLAP / (nine * den[x]) if some and own[x] > zero else _NONE


@kernel
def _directions(rh, vh, rv, vv, gh, gv):
    """The rows' and columns' estimates combined by the inverse of their expected squared errors
    m = variance plus the luminance's mean squared log step along the direction; (estimate, its
    expected squared error). Where the two disagree beyond m_h + m_v, one of them aliases beyond
    what the luminance shows: the excess (DerSimonian and Laird's between-estimates variance for
    two estimates, tau^2 = max(0, (r_h - r_v)^2 - m_h - m_v) / 2) is added to both."""
    zero, one, half = np.float32(0.0), np.float32(1.0), np.float32(0.5)
    if vh >= _NONE and vv >= _NONE:
        return zero, _NONE
    if vh >= _NONE:
        return rv, vv + gv
    if vv >= _NONE:
        return rh, vh + gh
    mh, mv = vh + gh, vv + gv
    d = rh - rv
    tau = max(d * d - mh - mv, zero) * half
    wh, wv = one / (mh + tau), one / (mv + tau)
    total = wh + wv
    return (wh * rh + wv * rv) / total, one / total


@kernel
def _choose(chosen, evidence, channels, share, rgb, luminance):
    """The garrote per pixel and ratio (module docstring) on the smoothed residuals (``chosen``,
    :func:`_residuals`) against their ``evidence``, into ``rgb`` and ``luminance`` in place; the
    arrays are a piece of rows."""
    zero, one, tiny = np.float32(0.0), np.float32(1.0), np.float32(1e-30)
    for r in range(rgb.shape[0]):
        da, db, va, vb = chosen[0, r], chosen[1, r], chosen[4, r], chosen[5, r]
        ea, eb, ch = evidence[0, r], evidence[1, r], channels[r]
        for x in range(rgb.shape[1]):
            beta_a = max(one - va[x] / max(ea[x], tiny), zero)
            beta_b = max(one - vb[x] / max(eb[x], tiny), zero)
            if beta_a <= zero and beta_b <= zero:
                continue
            red, green, blue = rgb[r, x, 0], rgb[r, x, 1], rgb[r, x, 2]
            a = np.log(red / green) + beta_a * da[x]
            b = np.log(blue / green) + beta_b * db[x]
            c = ch[x]
            if c == 0:
                green = red * np.exp(-a)
                blue = green * np.exp(b)
            elif c == 1:
                red = green * np.exp(a)
                blue = green * np.exp(b)
            else:
                green = blue * np.exp(-b)
                red = green * np.exp(a)
            rgb[r, x, 0], rgb[r, x, 1], rgb[r, x, 2] = red, green, blue
            luminance[r, x] = share[0] * red + share[1] * green + share[2] * blue
