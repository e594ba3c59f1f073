"""``weighted``: noise-optimal combination of every exposure's local interpolation (the default).

For each exposure level k, the uncensored pixels of that level give unbiased
radiance estimates x = s / e, and a binomial window that holds every phase of
the tile (3x3 for a 2x2 tile) interpolates them at every pixel:
m_k = sum_i G_i x_i / sum_i G_i over level-k pixels i. The levels are then
merged with inverse-variance weights of the Poisson-Gaussian model (sensor.py)
evaluated at the pixel's own predicted radiance L0:

    w_k = n_k e_k^2 / (e_k L0 / g + sigma^2),   L = sum_k w_k m_k / sum_k w_k

with n_k the level's share of the window. Two rules keep it unbiased:
- a level whose window holds any censored (saturated) pixel is left out at
  that pixel: its surviving pixels are the darker ones, so averaging them
  would bias the estimate low next to highlights;
- the weights of all pixels of one level are equal within the window, so a
  darker neighbour never counts for more than a brighter one.
L0 is the shot-noise maximum-likelihood estimate over the same window,
sum(s) / sum(e) over uncensored pixels. Where every level has a censored pixel
in the window, L0 itself is the result (it still uses every uncensored pixel),
raised to a censored pixel's own bound where it is lower;
where the window holds nothing uncensored, the result is the lower bound the
censored pixels imply. Nothing is tuned to an image: weights come from the
noise model, exclusions from the censoring alone.

The predicted variance (``return_variance``) is 1 / sum_k w_k n_eff,k / n_k, with
n_eff,k = (sum_i G_i)^2 / sum_i G_i^2 over the level's pixels in the window (a
level without pixels there adds nothing); where L0 is the result,
(L + sigma^2) / sum_i G_i e_i over the uncensored pixels; a lower bound's is its square.

Computation, per strip of rows. A compiled pass lays out the inputs of the
window sums as planes: per level k the samples x at that level's pixels (0
elsewhere, +inf at censored ones), then s and e at the uncensored pixels.
OpenCV sums each plane over the window (``smooth``); as the window's weights are
positive, a censored level-k pixel in the window turns plane k's sum into +inf,
which is the "left out at that pixel" test. A second compiled pass evaluates L0,
the weights and the merge per pixel. What the tile alone fixes (n_k, n_eff,k
and, for a strip without censored pixels, sum(G e)) is cached per strip shape.
"""

from __future__ import annotations

from concurrent.futures import Executor
from functools import lru_cache
from typing import NamedTuple

import numpy as np

from svelive.jit import flat, kernel
from svelive.methods.base import (Estimate, SveInput, binomial_kernel, censored_lower_bound, in_strips, smooth,
                                  support_size)
from svelive.pattern import Pattern


class _Layout(NamedTuple):
    """What the pattern alone fixes for the frames (strips) of one shape (H, W); cached, read-only.

    Window sums of the tile's layout repeat with the tile's rows except within
    a window of the top and bottom edges, so they are kept for the R rows of a
    small frame with the same edges (R = H for frames of a few tiles).

    exposures, squares: float32 (K,), the levels' nominal exposures e_k and e_k^2.
    rows: int64 (H,), the row of the arrays below that holds row r's values.
    index: uint8 (R, W), each pixel's level.
    share: float32 (K, R, W), n_k, the level's share of the window (0 where it has no pixel in it).
    information: float32 (K, R, W), n_eff,k / n_k (0 where n_k is 0).
    exposure_sum: float32 (R, W), sum_i G_i e_i over the window (the tile's exposures).
    """

    exposures: np.ndarray
    squares: np.ndarray
    rows: np.ndarray
    index: np.ndarray
    share: np.ndarray
    information: np.ndarray
    exposure_sum: np.ndarray


@lru_cache(maxsize=16)
def _level_layout(pattern: Pattern, shape: tuple[int, int]) -> _Layout:
    """The tile's window sums and level map for frames of ``shape`` (see _Layout), cached."""
    (th, tw), (h, w) = pattern.shape, shape
    window = support_size(th), support_size(tw)
    ky, kx = binomial_kernel(window[0]), binomial_kernel(window[1])
    edge = window[0] // 2  # rows a window reaches beyond its centre
    if h <= 2 * edge + 2 * th:
        small, rows = h, np.arange(h)
    else:
        # the top edge's rows, one tile of rows out of reach of both edges, the bottom edge's rows
        small = 2 * edge + th + (h - 2 * edge - th) % th
        rows = np.arange(h)
        rows[edge:h - edge] = edge + (rows[edge:h - edge] - edge) % th
        rows[h - edge:] -= h - small
    index = pattern.level_index_map((small, w))
    masks = [(index == k).astype(np.float32) for k in range(len(pattern.levels))]
    share = np.stack([smooth(mask, ky, kx) for mask in masks])
    square_sums = np.stack([smooth(mask, ky * ky, kx * kx) for mask in masks])
    effective = share * share / np.maximum(square_sums, np.float32(1e-12))
    information = np.divide(effective, share, out=np.zeros_like(share), where=share > 0)
    exposure_sum = smooth(Pattern(pattern.tile).exposure_map((small, w)), ky, kx)  # the nominal tile's
    layout = _Layout(pattern.levels.astype(np.float32), (pattern.levels * pattern.levels).astype(np.float32),
                     rows, index, share, information, exposure_sum)
    for array in layout:
        array.setflags(write=False)
    return layout


def run(inp: SveInput, *, return_variance: bool = False, workers: int | Executor = 1) -> Estimate:
    """``workers``: a thread count or an Executor for the frame's strips (base.map_on); the result does not depend on it."""
    halo = max(support_size(s) for s in inp.pattern.shape) // 2  # every window sum reaches this far
    # 48-96 rows are equally fast (measured); from 128 rows the K + 2 planes of a strip leave the caches
    return in_strips(_run, inp, halo, rows=64, workers=workers, return_variance=return_variance)


def _run(inp: SveInput, *, return_variance: bool = False) -> Estimate:
    th, tw = inp.pattern.shape
    window = (support_size(th), support_size(tw))
    ky, kx = binomial_kernel(window[0]), binomial_kernel(window[1])
    layout = _level_layout(inp.pattern, inp.shape)
    levels = layout.exposures.size
    h, w = inp.shape

    # Without censored pixels the plane of s is inp.signal itself and sum_i G_i e_i is the tile's,
    # cached (inp.exposure is the pattern's map: prepare and in_strips keep the tile's phase).
    tiled = inp.pattern.pixel_map is None and not inp.censored.any()
    planes = levels if tiled else levels + 2
    samples = np.empty((planes, h, w), np.float32)
    _lay_out_samples(*flat(inp.signal, inp.exposure, inp.censored), layout.index.reshape(-1), layout.rows, w,
                     samples.reshape(planes, -1), levels)
    sums = [smooth(plane, ky, kx).reshape(-1) for plane in samples]
    if tiled:
        sums.append(smooth(inp.signal, ky, kx).reshape(-1))
        exposure_sum, exposure_rows = layout.exposure_sum.reshape(-1), layout.rows
    else:
        exposure_sum, exposure_rows = sums.pop(), np.arange(h)

    gain, floor = inp.sensor.effective_gain, inp.sensor.floor_variance
    image = np.empty(inp.shape, np.float32)
    lower_bound = np.empty(inp.shape, bool)
    variance = np.empty(inp.shape, np.float32) if return_variance else np.empty(0, np.float32)
    bounds = _combine(tuple(sums), exposure_sum, exposure_rows, layout.share.reshape(levels, -1),
                      layout.information.reshape(levels, -1), layout.rows,
                      *flat(inp.signal, inp.exposure, inp.censored), layout.exposures, layout.squares,
                      np.float32(gain), np.float32(1.0 / gain), np.float32(floor), w,
                      *flat(image, lower_bound, variance))
    if bounds:
        where = np.nonzero(lower_bound)
        image[where] = censored_lower_bound(inp, window)[where]
        if return_variance:  # a bound is known to within itself: relative error 1
            variance[where] = image[where] ** 2
    return Estimate(image, lower_bound, variance if return_variance else None)


#: Pixels per block of the kernels' loops: their per-pixel temporaries stay in L1.
_BLOCK = 512


@kernel
def _lay_out_samples(signal, exposure, censored, index, rows, width, samples, levels):
    """Inputs of the window sums, samples (P, H * W) float32, one plane per channel.

    Planes 0..K-1: x = s / e at the pixels of that level (+inf if censored), 0
    elsewhere; when P = K + 2, plane K: s, plane K + 1: e, both 0 at censored pixels.
    index: (R * W) levels, row r's at rows[r] (``_Layout``).
    """
    zero, inf = np.float32(0.0), np.float32(np.inf)
    x = np.empty(_BLOCK, np.float32)
    for r in range(rows.size):
        for c0 in range(0, width, _BLOCK):
            n = min(width - c0, _BLOCK)
            at, t = r * width + c0, rows[r] * width + c0
            # 1-D views indexed from 0: the loops below vectorise (indexing at an offset did not)
            s, e, c, level = signal[at:at + n], exposure[at:at + n], censored[at:at + n], index[t:t + n]
            for i in range(n):
                x[i] = inf if c[i] else s[i] / e[i]
            if samples.shape[0] > levels:
                s_valid, e_valid = samples[levels][at:at + n], samples[levels + 1][at:at + n]
                for i in range(n):
                    s_valid[i] = zero if c[i] else s[i]
                    e_valid[i] = zero if c[i] else e[i]
            for k in range(levels):
                plane = samples[k][at:at + n]
                for i in range(n):
                    plane[i] = x[i] if level[i] == k else zero


@kernel
def _combine(sums, exposure_sum, exposure_rows, share, information, rows, signal, exposure, censored, exposures,
             squares, gain, inverse_gain, floor, width, image, lower_bound, variance):
    """L0, the level weights and their merge per pixel, from the window sums of ``_lay_out_samples``.

    sums: K + 1 flat float32 (H * W) window sums: the K levels' sum_i G_i x_i, then
    sum_i G_i s_i; exposure_sum: sum_i G_i e_i (R_e * W), row r's at exposure_rows[r];
    share, information: (K, R * W), row r's at rows[r] (``_Layout``). Writes image,
    lower_bound (H * W) and, when it is not empty, variance; returns the number of
    lower-bound pixels (no uncensored sample in the window), which the caller fills in.
    """
    levels = exposures.size
    want_variance = variance.size > 0
    zero, one, inf = np.float32(0.0), np.float32(1.0), np.float32(np.inf)
    tiny = np.float32(1e-30)
    first = np.empty(_BLOCK, np.float32)
    numerator = np.empty(_BLOCK, np.float32)
    denominator = np.empty(_BLOCK, np.float32)
    info = np.empty(_BLOCK, np.float32)
    bounds = 0
    for r in range(rows.size):
        for c0 in range(0, width, _BLOCK):
            n = min(width - c0, _BLOCK)
            at, t, te = r * width + c0, rows[r] * width + c0, exposure_rows[r] * width + c0
            # 1-D views indexed from 0: the loops below vectorise (indexing at an offset did not)
            signal_sum, e_sum = sums[levels][at:at + n], exposure_sum[te:te + n]
            for i in range(n):
                first[i] = max(signal_sum[i] / max(e_sum[i], tiny), zero) * inverse_gain  # L0 / g
                numerator[i] = zero
                denominator[i] = zero
                info[i] = zero
            for k in range(levels):
                # sum_i G_i x_i over level-k pixels (n_k m_k), +inf where one of them is censored
                interpolated, n_k, ratio = sums[k][at:at + n], share[k][t:t + n], information[k][t:t + n]
                e, e2 = exposures[k], squares[k]
                for i in range(n):
                    ok = interpolated[i] < inf
                    weight = e2 / (first[i] * e + floor)
                    numerator[i] += interpolated[i] * weight if ok else zero
                    weight *= n_k[i]
                    denominator[i] += weight if ok else zero
                    info[i] += weight * ratio[i] if ok else zero
            c, out, lower = censored[at:at + n], image[at:at + n], lower_bound[at:at + n]
            fallback = False
            for i in range(n):
                usable = denominator[i] > zero
                out[i] = max(numerator[i] / denominator[i] if usable else first[i] * gain, zero)
                fallback |= c[i] and not usable
                no_data = not e_sum[i] > zero
                lower[i] = no_data
                bounds += no_data
            if fallback:
                # Fallback pixels (every level censored somewhere in the window) hold L0, which
                # only the uncensored, darker side of an edge informs; a censored pixel there
                # knows it is at least its own bound, so it keeps that.
                s, e = signal[at:at + n], exposure[at:at + n]
                for i in range(n):
                    if c[i] and not denominator[i] > zero:
                        out[i] = max(out[i], s[i] / e[i])
            if want_variance:
                var = variance[at:at + n]
                for i in range(n):
                    usable = denominator[i] > zero
                    var[i] = one / info[i] if usable else (out[i] + floor) / max(e_sum[i], tiny)
    return bounds
