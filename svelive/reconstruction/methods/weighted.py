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

Computation, per strip of rows: OpenCV makes the window sums, a compiled pass
evaluates L0, the weights, the merge and the variance per pixel. Censored
pixels enter the sums as +inf: as the window's weights are positive, a censored
level-k pixel in the window turns level k's sum into +inf, which is the "left
out at that pixel" test. Level k's sum of s is e_k times its sum of x; in a
strip without censored pixels sum(s) is the levels' sums added up and sum(G e)
the tile's, otherwise s and e at the uncensored pixels get window sums of
their own. What the tile alone fixes (n_k, n_eff,k, sum(G e)) is cached per strip shape.

Level sums, polyphase: in the [1,2,1]/4 window of a tile of at most 2x2, the pixels
at offsets of one class per axis (0; -1 and +1) share one tile phase, so each level's sum
is s, Hs = s(c-1) + s(c+1), Vs (the same along rows) or Ds (Vs of Hs), times 1/4, 1/8, 1/8
or 1/16, picked by the pixel's phase (a fixed sum of them for a level on several phases):
three shifted additions instead of K window sums. Reflect-101 keeps the class's phase at
the frame's edges (row -1 reads row 1), so the sums are exact there too. The general way,
for longer tiles (whose reflected edges change phase), frames of a single row or column
under a 2-row or 2-column tile, a level on 3 of 4 phases and per-pixel exposures (a calibrated
map, or a colour frame's luminance with its channels folded into them, SveInput.folded):
a compiled pass lays out one plane per level (x at its pixels, 0 elsewhere), OpenCV sums each.
A folded frame's level holds pixels of different exposures (a channel of tiny share has a tiny
e' and a reading that says little), so its mean is sum G s / sum G e' and its weight takes the
level's mean exposure in the window (_folded_sums); calibrated maps keep the mean of x.
"""

from __future__ import annotations

from concurrent.futures import Executor
from functools import lru_cache
from typing import NamedTuple

import cv2
import numpy as np

from svelive.core.pattern import Pattern
from svelive.jit import flat, kernel
from svelive.reconstruction.methods.base import (
    Estimate,
    SveInput,
    binomial_kernel,
    fill_lower_bounds,
    in_strips,
    smooth,
    support_size,
    tile_rows,
)


class _Layout(NamedTuple):
    """What the pattern alone fixes for the frames (strips) of one shape (H, W); cached, read-only.

    Window sums of the tile's layout repeat with the tile's rows except within
    a window of the top and bottom edges, so they are kept for the R rows of a
    small frame with the same edges (R = H for frames of a few tiles).

    The window sums come as P planes (module docstring): one per level (of x),
    or with ``polyphase`` s and its neighbour sums, those of one group added up;
    either way each plane holds one level's sum at every pixel, but which level
    may change from pixel to pixel. The per-level arrays below are per plane,
    holding that pixel's level's values.

    rows: int64 (H,), the row of the arrays below that holds row r's values.
    index: uint8 (R, W), each pixel's level.
    polyphase: True when the planes come from s and its neighbour sums.
    groups: the neighbour sums (0: s, then Hs, Vs, Ds, those the tile has) added into each plane.
    scales: float32 (P,), what turns a plane into its level's sum_i G_i s_i: the window weight
        of its pixels (1 where a group's are folded in), or e_k for a level's window sum of x.
    exposures: float32 (P, T, W), the plane's level's nominal exposure e_k on rows of tile phase
        r % T (T = 1 when the planes' levels do not depend on the row).
    share: float32 (P, R, W), n_k, the level's share of the window (0 where it has no pixel in it).
    information: float32 (P, R, W), n_eff,k / n_k (0 where n_k is 0).
    exposure_sum: float32 (R, W), sum_i G_i e_i over the window (the tile's exposures).
    """

    rows: np.ndarray
    index: np.ndarray
    polyphase: bool
    groups: tuple[tuple[int, ...], ...]
    scales: np.ndarray
    exposures: np.ndarray
    share: np.ndarray
    information: np.ndarray
    exposure_sum: np.ndarray


@lru_cache(maxsize=16)
def _level_layout(pattern: Pattern, shape: tuple[int, int], folded: bool = False) -> _Layout:
    """The tile's window sums and level map for frames of ``shape`` (see _Layout), cached.

    ``folded``: the exposures are per pixel, off the levels (SveInput.folded), so the
    level sums cannot come from s alone: the general way.
    """
    (th, tw), (h, w) = pattern.shape, shape
    window = support_size(th), support_size(tw)
    ky, kx = binomial_kernel(window[0]), binomial_kernel(window[1])
    small, rows = tile_rows(h, th, window[0] // 2)
    levels = pattern.levels
    index = pattern.level_index_map((small, w))
    masks = [(index == k).astype(np.float32) for k in range(levels.size)]
    share = np.stack([smooth(mask, ky, kx) for mask in masks])
    square_sums = np.stack([smooth(mask, ky * ky, kx * kx) for mask in masks])
    effective = share * share / np.maximum(square_sums, np.float32(1e-12))
    information = np.divide(effective, share, out=np.zeros_like(share), where=share > 0)
    exposure_sum = smooth(Pattern(pattern.tile).exposure_map((small, w)), ky, kx)  # the nominal tile's

    groups = _phase_groups(pattern) if _polyphase(pattern, shape) and not folded else None
    if groups is None:  # plane k: level k's window sum of x
        owner = np.broadcast_to(np.arange(levels.size)[:, None, None], (levels.size, small, w))
        groups, scales, phase_rows = (), levels.astype(np.float32), 1
    else:
        # plane g holds the level of the pixels at offsets of its class (cy, cx): phase (r + cy, c + cx)
        classes, weights = _classes(pattern.shape), _class_weights(pattern.shape)
        shifted = pattern.level_index_map((small + 1, w + 1))
        owner = np.stack([shifted[cy:cy + small, cx:cx + w] for cy, cx in (classes[g[0]] for g in groups)])
        scales, phase_rows = np.array([weights[g[0]] if len(g) == 1 else 1 for g in groups], np.float32), th
    owner = owner.astype(np.intp)
    pick = lambda per_level: np.take_along_axis(per_level, owner, axis=0)  # noqa: E731
    # the planes' exposures repeat with the tile's rows (owner's first rows: small >= th), kept small to stay in cache
    exposures = np.ascontiguousarray(levels.astype(np.float32)[owner[:, :phase_rows]])
    layout = _Layout(rows, index, bool(groups), groups, scales, exposures, pick(share), pick(information),
                     exposure_sum)
    for array in layout:
        if isinstance(array, np.ndarray):
            array.setflags(write=False)
    return layout


def _polyphase(pattern: Pattern, shape: tuple[int, int]) -> bool:
    """Whether s and its neighbour sums can make the level sums for frames of ``shape`` (module docstring).

    Needs a period of at most 2 per axis (reflect-101 keeps a pixel's phase along
    such an axis only: row -1 reads row 1), at least 2 pixels along an axis of
    period 2 (a single row reflects onto itself) and the tile's exposures.
    """
    return (pattern.pixel_map is None and max(pattern.shape) <= 2
            and all(n >= 2 or t == 1 for t, n in zip(pattern.shape, shape)))


def _classes(tile_shape: tuple[int, int]) -> list[tuple[int, int]]:
    """Offset classes (cy, cx) of the neighbour sums s, Hs, Vs, Ds of a tile of at most 2x2 (those it has).

    Class 0 of an axis is the centre, class 1 the offsets -1 and +1; at a pixel of phase
    (py, px) a class's pixels all have phase ((py + cy) % th, (px + cx) % tw).
    """
    return [(cy, cx) for cy in range(tile_shape[0]) for cx in range(tile_shape[1])]


def _class_weights(tile_shape: tuple[int, int]) -> list[float]:
    """Window weight of each pixel of each class (_classes): 1/4, 1/8, 1/8, 1/16 for a 2x2 tile."""
    ty, tx = binomial_kernel(support_size(tile_shape[0])), binomial_kernel(support_size(tile_shape[1]))
    return [float(ty[tile_shape[0] // 2 + cy] * tx[tile_shape[1] // 2 + cx]) for cy, cx in _classes(tile_shape)]


def _phase_groups(pattern: Pattern) -> tuple[tuple[int, ...], ...] | None:
    """The neighbour sums that belong to one level at every pixel, grouped, or None.

    Sums (classes) c and c' always share a level when the tile repeats under a
    shift by c - c' (a checkerboard: s and Ds, Hs and Vs). None when a level owns
    more than one group at some pixel (a level on 3 of the 4 phases of a 2x2 tile):
    those take the general way.
    """
    th, tw = pattern.shape
    tile = pattern.level_index_map((th, tw))
    classes = _classes((th, tw))
    owners = [tuple(int(tile[(py + cy) % th, (px + cx) % tw]) for py in range(th) for px in range(tw))
              for cy, cx in classes]  # class -> its level at each pixel phase
    groups: dict[tuple[int, ...], list[int]] = {}
    for j, owner in enumerate(owners):
        groups.setdefault(owner, []).append(j)
    one_each = all(len({owner[p] for owner in groups}) == len(groups) for p in range(th * tw))
    return tuple(tuple(g) for g in groups.values()) if one_each else None


def _neighbour_sums(base: np.ndarray, tile_shape: tuple[int, int]) -> list[np.ndarray]:
    """[s, Hs, Vs, Ds] (those the tile has, see _classes) from base = s, float32 (H, W) each."""
    th, tw = tile_shape
    sums = [base]
    if tw == 2:
        sums.append(_neighbour_sum(base, axis=1))
    if th == 2:
        sums.append(_neighbour_sum(base, axis=0))
    if th == 2 and tw == 2:
        sums.append(_neighbour_sum(sums[1], axis=0))
    return sums


def _neighbour_sum(a: np.ndarray, axis: int) -> np.ndarray:
    """a(-1) + a(+1) along ``axis`` (2 or more pixels long), borders reflect-101; float32 (H, W).

    Shifted views added, not a [1, 0, 1] filter: the filter's 0 tap times a
    censored pixel's +inf would be NaN.
    """
    out = np.empty_like(a)
    if axis == 1:
        if a.shape[1] > 2:
            cv2.add(a[:, :-2], a[:, 2:], dst=out[:, 1:-1])
        np.add(a[:, 1], a[:, 1], out=out[:, 0])
        np.add(a[:, -2], a[:, -2], out=out[:, -1])
    else:
        if a.shape[0] > 2:
            cv2.add(a[:-2], a[2:], dst=out[1:-1])
        np.add(a[1], a[1], out=out[0])
        np.add(a[-2], a[-2], out=out[-1])
    return out


def _group_sums(sums: list[np.ndarray], groups: tuple[tuple[int, ...], ...],
                tile_shape: tuple[int, int]) -> list[np.ndarray]:
    """The planes of ``groups`` from the neighbour sums: a lone sum as it is, a group's weighted sum (new array)."""
    weight = _class_weights(tile_shape)
    planes = []
    for group in groups:
        plane = sums[group[0]]
        if len(group) > 1:
            plane = cv2.addWeighted(plane, weight[group[0]], sums[group[1]], weight[group[1]], 0.0)
            for j in group[2:]:
                cv2.addWeighted(plane, 1.0, sums[j], weight[j], 0.0, dst=plane)
        planes.append(plane)
    return planes


def run(inp: SveInput, *, return_variance: bool = False, workers: int | Executor = 1) -> Estimate:
    """``workers``: a thread count or an Executor for the frame's strips (base.map_on); the result does not depend on it."""
    halo = max(support_size(s) for s in inp.pattern.shape) // 2  # every window sum reaches this far
    # 48-96 rows are equally fast (measured, both ways of summing); from 128 rows a strip's planes leave the caches
    return in_strips(_run, inp, halo, rows=64, workers=workers, return_variance=return_variance)


def _run(inp: SveInput, *, return_variance: bool = False) -> Estimate:
    th, tw = inp.pattern.shape
    window = (support_size(th), support_size(tw))
    ky, kx = binomial_kernel(window[0]), binomial_kernel(window[1])
    layout = _level_layout(inp.pattern, inp.shape, inp.folded)
    h, w = inp.shape

    # Without censored pixels sum(s) is the levels' sums added up and sum_i G_i e_i is the tile's,
    # cached (inp.exposure is the pattern's map: prepare and in_strips keep the tile's phase).
    tiled = inp.pattern.pixel_map is None and not inp.folded and not inp.censored.any()
    valid = np.empty((2, 0 if tiled else h * w), np.float32)
    if layout.polyphase:
        if tiled:
            signal = inp.signal
        else:  # +inf at censored pixels
            signal = np.empty((h, w), np.float32)
            _lay_out_samples(*flat(inp.signal, inp.exposure, inp.censored), np.zeros(w, np.uint8),
                             np.zeros(h, np.int64), w, signal.reshape(1, -1), valid[0], valid[1], False)
        planes = _group_sums(_neighbour_sums(signal, (th, tw)), layout.groups, (th, tw))
    elif inp.folded:
        planes, scales, exposures = _folded_sums(inp, layout, valid, ky, kx)
    else:
        levels = layout.scales.size
        samples = np.empty((levels, h, w), np.float32)
        _lay_out_samples(*flat(inp.signal, inp.exposure, inp.censored), layout.index.reshape(-1), layout.rows, w,
                         samples.reshape(levels, -1), valid[0], valid[1], True)
        planes = [smooth(plane, ky, kx) for plane in samples]
    if tiled:
        signal_sum = valid[0]  # empty: the kernel adds up the levels' sums of s
        exposure_sum, exposure_rows = layout.exposure_sum.reshape(-1), layout.rows
    else:
        signal_sum = smooth(valid[0].reshape(h, w), ky, kx).reshape(-1)
        exposure_sum, exposure_rows = smooth(valid[1].reshape(h, w), ky, kx).reshape(-1), np.arange(h)

    gain, floor = inp.sensor.effective_gain, inp.sensor.floor_variance
    image = np.empty(inp.shape, np.float32)
    lower_bound = np.empty(inp.shape, bool)
    variance = np.empty(inp.shape, np.float32) if return_variance else np.empty(0, np.float32)
    count = layout.scales.size
    if not inp.folded:
        scales, exposures = layout.scales, layout.exposures
    bounds = _combine(tuple(_read_only(plane.reshape(-1)) for plane in planes), scales, exposures,
                      layout.share.reshape(count, -1), layout.information.reshape(count, -1), layout.rows,
                      signal_sum, exposure_sum, exposure_rows, *flat(inp.signal, inp.exposure, inp.censored),
                      np.float32(gain), np.float32(1.0 / gain), np.float32(floor), w,
                      *flat(image, lower_bound, variance))
    if bounds:
        fill_lower_bounds(inp, lower_bound, window, image, variance if return_variance else None)
    return Estimate(image, lower_bound, variance if return_variance else None)


def _folded_sums(inp: SveInput, layout: _Layout, valid: np.ndarray, ky: np.ndarray,
                 kx: np.ndarray) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
    """Level sums for exposures off the levels (SveInput.folded): (planes, scales, exposures) for _combine.

    A level's pixels no longer share one exposure (a colour frame's channels are folded in, and
    a channel with a tiny share has a tiny e' and a reading that says little), so its mean is the
    shot-noise maximum-likelihood m_k = sum_i G_i s_i / sum_i G_i e'_i rather than the mean of the
    x_i, and its weight takes the level's mean exposure over the window, e_k = sum_i G_i e'_i / n_k,
    per pixel: the planes hold sum_i G_i s_i (= e_k n_k m_k, scale 1) and ``exposures`` (K, H, W) e_k
    (row r's at r, the kernel's row phase of an H-row tile). ``valid`` receives s and e at the
    uncensored pixels, as for the other frames off the tile.
    """
    h, w = inp.shape
    levels = layout.scales.size
    samples = np.empty((levels, h, w), np.float32)
    exposures = np.empty((levels, h, w), np.float32)
    index = layout.index.reshape(-1)
    _lay_out_samples(*flat(inp.signal, inp.exposure, inp.censored), index, layout.rows, w,
                     samples.reshape(levels, -1), valid[0], valid[1], False)
    none = np.empty(0, np.float32)
    _lay_out_samples(*flat(inp.exposure, inp.exposure, inp.censored), index, layout.rows, w,
                     exposures.reshape(levels, -1), none, none, False)
    planes = [smooth(plane, ky, kx) for plane in samples]
    for k in range(levels):
        _mean_exposure(smooth(exposures[k], ky, kx), layout.share[k], layout.rows, exposures[k])
    return planes, np.ones(levels, np.float32), exposures


@kernel
def _mean_exposure(exposure_sum, share, rows, out):
    """out (H, W) = a level's window sum of e' over its share n_k (R, W; row r's at rows[r]), 0 where n_k is 0."""
    zero = np.float32(0.0)
    for r in range(out.shape[0]):
        total, n, o = exposure_sum[r], share[rows[r]], out[r]
        for x in range(o.size):
            ok = n[x] > zero
            o[x] = total[x] / n[x] if ok else zero


def _read_only(a: np.ndarray) -> np.ndarray:
    """A read-only view: the kernel indexes its planes as one tuple type, and inp.signal may be one of them."""
    view = a.view()
    view.setflags(write=False)
    return view


#: Pixels per block of the kernels' loops: their per-pixel temporaries stay in L1.
_BLOCK = 512


@kernel
def _lay_out_samples(signal, exposure, censored, index, rows, width, samples, valid_signal, valid_exposure,
                     radiance):
    """Inputs of the window sums: samples (P, H * W) float32, one plane per level.

    Plane k: x = s / e (``radiance``; else s) at the pixels of level k, +inf at
    censored ones, 0 elsewhere, with index: (R * W) levels, row r's at rows[r]
    (``_Layout``); a zero index and P = 1 give every pixel's. When valid_signal
    and valid_exposure (H * W) are not empty: s and e, both 0 at censored pixels.
    """
    zero, inf = np.float32(0.0), np.float32(np.inf)
    levels = samples.shape[0]
    x = np.empty(_BLOCK, np.float32)
    for r in range(rows.size):
        for c0 in range(0, width, _BLOCK):
            n = min(width - c0, _BLOCK)
            at, t = r * width + c0, rows[r] * width + c0
            # 1-D views indexed from 0: the loops below vectorise (indexing at an offset did not)
            s, e, c, level = signal[at:at + n], exposure[at:at + n], censored[at:at + n], index[t:t + n]
            if radiance:
                for i in range(n):
                    x[i] = inf if c[i] else s[i] / e[i]
            else:
                for i in range(n):
                    x[i] = inf if c[i] else s[i]
            if valid_signal.size > 0:
                s_valid, e_valid = valid_signal[at:at + n], valid_exposure[at:at + n]
                for i in range(n):
                    s_valid[i] = zero if c[i] else s[i]
                    e_valid[i] = zero if c[i] else e[i]
            for k in range(levels):
                plane = samples[k][at:at + n]
                for i in range(n):
                    plane[i] = x[i] if level[i] == k else zero


@kernel
def _combine(planes, scales, exposures, share, information, rows, signal_sum, exposure_sum, exposure_rows,
             signal, exposure, censored, gain, inverse_gain, floor, width, image, lower_bound, variance):
    """L0, the level weights and their merge per pixel, from the window sums.

    planes: P flat read-only float32 (H * W) window sums; scales[p] * planes[p] is one
    level's sum_i G_i s_i over its pixels (e_k n_k m_k, +inf where one of them is
    censored), that level's e_k is exposures (P, T, W), row r's at r % T, and its n_k
    and n_eff,k / n_k are share, information (P, R * W), row r's at rows[r] (``_Layout``).
    signal_sum: sum_i G_i s_i (H * W), or empty: the levels' sums added up (no censored
    pixel). exposure_sum: sum_i G_i e_i (R_e * W), row r's at exposure_rows[r]. Writes
    image, lower_bound (H * W) and, when it is not empty, variance; returns the number
    of lower-bound pixels (no uncensored sample in the window), which the caller fills in.
    """
    want_variance = variance.size > 0
    zero, one, inf = np.float32(0.0), np.float32(1.0), np.float32(np.inf)
    tiny = np.float32(1e-30)
    first = np.empty(_BLOCK, np.float32)
    numerator = np.empty(_BLOCK, np.float32)
    denominator = np.empty(_BLOCK, np.float32)
    info = np.empty(_BLOCK, np.float32)
    bounds = 0
    for r in range(rows.size):
        phase = r % exposures.shape[1]
        for c0 in range(0, width, _BLOCK):
            n = min(width - c0, _BLOCK)
            at, t, te = r * width + c0, rows[r] * width + c0, exposure_rows[r] * width + c0
            # 1-D views indexed from 0: the loops below vectorise (indexing at an offset did not)
            e_sum = exposure_sum[te:te + n]
            if signal_sum.size > 0:
                s_sum = signal_sum[at:at + n]
                for i in range(n):
                    first[i] = s_sum[i]
            else:
                for i in range(n):
                    first[i] = zero
                for p in range(len(planes)):
                    plane, scale = planes[p][at:at + n], scales[p]
                    for i in range(n):
                        first[i] += plane[i] * scale
            for i in range(n):
                first[i] = max(first[i] / max(e_sum[i], tiny), zero) * inverse_gain  # L0 / g
                numerator[i] = zero
                denominator[i] = zero
                info[i] = zero
            for p in range(len(planes)):
                plane, scale = planes[p][at:at + n], scales[p]
                e, n_k, ratio = exposures[p][phase][c0:c0 + n], share[p][t:t + n], information[p][t:t + n]
                for i in range(n):
                    level_sum = plane[i] * scale  # e_k n_k m_k
                    ok = level_sum < inf
                    weight = e[i] / (first[i] * e[i] + floor)  # w_k / (e_k n_k)
                    numerator[i] += level_sum * weight if ok else zero
                    weight *= e[i] * n_k[i]  # w_k
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
