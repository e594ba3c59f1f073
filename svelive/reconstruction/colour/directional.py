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

import cv2
import numpy as np

from svelive.jit import kernel
from svelive.reconstruction.colour.cells import CellLayout
from svelive.reconstruction.colour.lattice import F_HIGH, F_LOW
from svelive.reconstruction.colour.sites import applies
from svelive.reconstruction.methods.base import SveInput

_BORDER = cv2.BORDER_REFLECT_101  # mirrored about the edge pixel: the CFA parity is kept
_ONE = np.ones(1, np.float32)
#: Step 1: the two neighbours' mean plus a quarter of the site's second difference, along one direction.
_GREEN = np.array([-0.25, 0.5, 0.5, 0.5, -0.25], np.float32)


def _window() -> np.ndarray:
    """Step 2's window (correlation, float32 5x5) over the row gradients |C(x) - C(x + 2)|: the gradients
    that lie inside the 5x5 around the pixel, those of its own colour's rows (-2, 0, +2; the centre row
    weighted 3) at columns -2 and 0, those of the other colour's rows (-1, +1) at column -1."""
    k = np.zeros((5, 5), np.float32)
    for dy, weight in ((-2, 1.0), (0, 3.0), (2, 1.0)):
        k[2 + dy, 0] = k[2 + dy, 2] = weight
    k[1, 1] = k[3, 1] = 1.0
    return k


_ROWS_WINDOW = _window()
_COLS_WINDOW = np.ascontiguousarray(_ROWS_WINDOW.T)


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
    return cv2.merge(demosaic_planes(mosaic, red, refine)[:3])


def demosaic_planes(mosaic: np.ndarray, red: tuple[int, int], refine: bool = True):
    """:func:`demosaic_log` as three float32 (H, W) planes R, G, B, and the decision (uint8 (H, W), 1 where
    green was interpolated along the rows)."""
    m = np.ascontiguousarray(mosaic, dtype=np.float32)
    ry, rx = red
    g_rows = cv2.sepFilter2D(m, cv2.CV_32F, _GREEN, _ONE, borderType=_BORDER)
    g_cols = cv2.sepFilter2D(m, cv2.CV_32F, _ONE, _GREEN, borderType=_BORDER)
    d_rows, d_cols = np.empty_like(m), np.empty_like(m)
    _gradients(m, g_rows, g_cols, ry, rx, d_rows, d_cols)
    s_rows = cv2.filter2D(d_rows, cv2.CV_32F, _ROWS_WINDOW, borderType=cv2.BORDER_CONSTANT)
    s_cols = cv2.filter2D(d_cols, cv2.CV_32F, _COLS_WINDOW, borderType=cv2.BORDER_CONSTANT)
    g, r, b = d_rows, d_cols, np.empty_like(m)  # (the gradients are spent)
    horizontal = np.empty(m.shape, np.uint8)
    _decide(g_rows, g_cols, s_rows, s_cols, g, horizontal)
    _at_green(m, g, r, b, ry, rx)
    _at_opposite(m, r, b, horizontal, ry, rx, np.float32(0.0))
    if refine:
        _refine_green(m, r, g, b, horizontal, ry, rx)
        _at_green(m, g, r, b, ry, rx)
        _at_opposite(m, r, b, horizontal, ry, rx, np.float32(1.0))
    return r, g, b, horizontal


@kernel(inline="always")
def _mirror(i, n):
    """Index ``i`` mirrored about the edge pixels of 0 .. n - 1 (keeps the CFA parity)."""
    if i < 0:
        return -i
    if i >= n:
        return 2 * n - 2 - i
    return i


@kernel(inline="always")
def _beside(rows, y, x, h, w):
    """(y0, x0, y1, x1): the two pixels beside (y, x) along the row (``rows``) or the column, mirrored."""
    if rows:
        return y, _mirror(x - 1, w), y, _mirror(x + 1, w)
    return _mirror(y - 1, h), x, _mirror(y + 1, h), x


@kernel
def _gradients(m, g_rows, g_cols, ry, rx, d_rows, d_cols):
    """Step 2's gradients: at a red or blue site |C(x) - C(x + 2)| of the colour difference C = X - G along
    rows (``d_rows``) and columns (``d_cols``); 0 at the green sites (C is 0 there), where ``g_rows`` and
    ``g_cols`` become the site's own value (in place; the gradients read red and blue sites only)."""
    h, w = m.shape
    zero = np.float32(0.0)
    for y in range(h):
        red_row = y % 2 == ry
        yy = _mirror(y + 2, h)
        for x in range(w):
            if red_row != (x % 2 == rx):  # a green site: its own value, no gradient
                g_rows[y, x] = g_cols[y, x] = m[y, x]
                d_rows[y, x] = zero
                d_cols[y, x] = zero
                continue
            xx = _mirror(x + 2, w)
            d_rows[y, x] = abs((m[y, x] - g_rows[y, x]) - (m[y, xx] - g_rows[y, xx]))
            d_cols[y, x] = abs((m[y, x] - g_cols[y, x]) - (m[yy, x] - g_cols[yy, x]))


@kernel
def _decide(g_rows, g_cols, s_rows, s_cols, g, horizontal):
    """Green along the rows where the columns' window sum is at least the rows', else along the columns."""
    h, w = g.shape
    for y in range(h):
        for x in range(w):
            rows = s_cols[y, x] >= s_rows[y, x]
            horizontal[y, x] = rows
            g[y, x] = g_rows[y, x] if rows else g_cols[y, x]


@kernel
def _at_green(m, g, r, b, ry, rx):
    """Red and blue at the green sites (green plus the mean of X - G over the two X sites beside it: along
    the row where the row holds X, along the column elsewhere); each site's own value at its own site."""
    h, w = m.shape
    half = np.float32(0.5)
    for y in range(h):
        red_row = y % 2 == ry
        up, down = _mirror(y - 1, h), _mirror(y + 1, h)
        for x in range(w):
            red_col = x % 2 == rx
            if red_row and red_col:
                r[y, x] = m[y, x]
            elif not red_row and not red_col:
                b[y, x] = m[y, x]
            else:
                left, right = _mirror(x - 1, w), _mirror(x + 1, w)
                across = half * ((m[y, left] - g[y, left]) + (m[y, right] - g[y, right]))
                along = half * ((m[up, x] - g[up, x]) + (m[down, x] - g[down, x]))
                if red_row:
                    r[y, x] = g[y, x] + across
                    b[y, x] = g[y, x] + along
                else:
                    r[y, x] = g[y, x] + along
                    b[y, x] = g[y, x] + across


@kernel
def _at_opposite(m, r, b, horizontal, ry, rx, centre):
    """Red at the blue sites and blue at the red sites: the site's value plus (minus) the mean of R - B
    over its two green neighbours along the chosen direction, and the site's own R - B with weight
    ``centre`` (0 in step 3, 1 in the refinement's three-pixel mean). Reads R - B at green sites only
    besides the site itself, so it works in place."""
    h, w = m.shape
    for y in range(h):
        red_row = y % 2 == ry
        for x in range(w):
            red_col = x % 2 == rx
            if red_row != red_col:
                continue
            y0, x0, y1, x1 = _beside(horizontal[y, x], y, x, h, w)
            diff = (r[y0, x0] - b[y0, x0]) + (r[y1, x1] - b[y1, x1])
            if centre > np.float32(0.0):  # (the site's other channel is not set before step 3)
                diff += centre * (r[y, x] - b[y, x])
            diff /= np.float32(2.0) + centre
            if red_row:
                b[y, x] = m[y, x] - diff
            else:
                r[y, x] = m[y, x] + diff


@kernel
def _refine_green(m, r, g, b, horizontal, ry, rx):
    """The refinement of green at the red and blue sites: the site's value minus the three-pixel mean of
    X - G along the chosen direction (its neighbours are green sites, which it does not write)."""
    h, w = m.shape
    third = np.float32(1.0 / 3.0)
    for y in range(h):
        red_row = y % 2 == ry
        for x in range(w):
            red_col = x % 2 == rx
            if red_row != red_col:
                continue
            y0, x0, y1, x1 = _beside(horizontal[y, x], y, x, h, w)
            if red_row:
                diff = (r[y0, x0] - g[y0, x0]) + (r[y1, x1] - g[y1, x1]) + (m[y, x] - g[y, x])
            else:
                diff = (b[y0, x0] - g[y0, x0]) + (b[y1, x1] - g[y1, x1]) + (m[y, x] - g[y, x])
            g[y, x] = m[y, x] - third * diff


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


def weights(inp: SveInput, rgb: np.ndarray, own: np.ndarray) -> np.ndarray:
    """float32 (H, W): the demosaiced channels' weight (module docstring, Where): the lattice blend of the
    3x3's smallest own share, times the 5x5 mean of the sites' m^2 / (m^2 + v), 0 within a pixel of a
    censored reading. ``own``: float32 (H, W), filled here with each pixel's own channel of ``rgb``."""
    f32 = np.float32
    share, snr = np.empty_like(own), np.empty_like(own)
    sensor = inp.sensor
    _site_terms(rgb, inp.channels, np.asarray(inp.exposure, f32), f32(1.0 / sensor.effective_gain),
                f32(sensor.floor_variance), own, share, snr)
    smallest = cv2.erode(share, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)
    blend = np.clip((smallest - f32(F_LOW)) * f32(1.0 / (F_HIGH - F_LOW)), f32(0.0), f32(1.0))
    weight = cv2.multiply(blend, cv2.blur(snr, (5, 5), borderType=cv2.BORDER_REFLECT))
    near = cv2.dilate(inp.censored.view(np.uint8), np.ones((3, 3), np.uint8))
    weight[near.view(bool)] = 0
    return weight


@kernel
def _site_terms(rgb, channels, exposure, inverse_gain, floor_variance, own, share, snr):
    """Per pixel: its own channel's value m, its share of its brightest channel (1 where all are 0), and
    m^2 / (m^2 + v), v = (e m / g + floor variance) / e^2 the noise model's variance at its exposure e."""
    h, w = own.shape
    zero, one = np.float32(0.0), np.float32(1.0)
    for y in range(h):
        for x in range(w):
            m = rgb[y, x, channels[y, x]]
            top = max(rgb[y, x, 0], max(rgb[y, x, 1], rgb[y, x, 2]))
            own[y, x] = m
            share[y, x] = m / top if top > zero else one
            level = max(m, zero)
            e = exposure[y, x]
            variance = (e * level * inverse_gain + floor_variance) / (e * e)
            snr[y, x] = level * level / (level * level + variance)


def directional_channels(inp: SveInput, luminance: np.ndarray, rgb: np.ndarray, share: np.ndarray,
                         floor: float, refine: bool = True) -> bool:
    """The stage (module docstring) into ``rgb`` (float32 (H, W, 3), linear, DN at exposure 1) and
    ``luminance`` (float32 (H, W), Y), in place. ``share``: n_c of the CFA. ``floor``: the logarithm's
    floor (DN at exposure 1; the longest exposure's read-noise floor). Each pixel keeps its own channel.
    Returns False (nothing done) where it does not apply (not a 2x2 Bayer CFA, a frame under 5x5)."""
    h, w = luminance.shape
    red = red_site(inp)
    if red is None or h < 5 or w < 5 or inp.channels is None:
        return False
    channels = inp.channels
    own = np.empty(luminance.shape, np.float32)
    weight = weights(inp, rgb, own)
    if cv2.countNonZero(weight) == 0:
        return True
    fl = np.float32(floor)
    r, g, b, _ = demosaic_planes(cv2.log(np.maximum(own, 0) + fl), red, refine)
    _blend(rgb, luminance, r, g, b, channels, weight, fl, np.asarray(share, np.float32))
    return True


@kernel
def _blend(rgb, luminance, r, g, b, channels, weight, floor, share):
    """At each pixel of nonzero ``weight``: its other two channels move by the weight towards exp of the
    demosaiced logarithms minus ``floor`` (at least 0), and the luminance becomes sum_c n_c RGB_c."""
    h, w = luminance.shape
    zero = np.float32(0.0)
    for y in range(h):
        for x in range(w):
            wt = weight[y, x]
            if wt <= zero:
                continue
            own = channels[y, x]
            for c in range(3):
                if c == own:
                    continue
                plane = r if c == 0 else g if c == 1 else b
                value = max(np.exp(plane[y, x]) - floor, zero)
                rgb[y, x, c] += wt * (value - rgb[y, x, c])
            luminance[y, x] = share[0] * rgb[y, x, 0] + share[1] * rgb[y, x, 1] + share[2] * rgb[y, x, 2]
