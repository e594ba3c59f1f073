"""Step 5 of ``adaptive``: where the window's result cannot tell the level from 0, the levels of wider blocks that
are flat within their noise (:func:`wide_fallback`), only over the strips holding such pixels."""

from __future__ import annotations

from concurrent.futures import Executor
from typing import NamedTuple

import cv2
import numpy as np

from svelive.jit import flat, kernel
from svelive.reconstruction.methods.adaptive.parameters import CONTRAST_SIGMA, TINY
from svelive.reconstruction.methods.adaptive.posterior import posterior_at, posterior_polynomial
from svelive.reconstruction.methods.base import SveInput, count_true, map_on, reflect_101, true_positions


#: Scales of the wide fallback (:func:`wide_fallback`): blocks of the window's size, then 3 times it, ...
WIDE_SCALES = 2
#: The wide fallback takes box filters over a band of rows once its active pixels times a block's pixels times
#: this exceed the band's pixels; below, each active pixel sums its eight blocks itself (:func:`_wide_direct`).
#: Eight: a pixel read per block pixel taken to cost about a box-filtered pixel of the band (not tuned).
WIDE_DIRECT = 8
#: Strips the wide fallback takes together (one band of rows, its box filters reaching beyond it only once).
WIDE_GROUP = 4


class Dark(NamedTuple):
    """What the wide fallback (:func:`wide_fallback`) needs of a strip's rows, float32 (rows, W) unless said.

    ``weights``: the readings' inverse variances as the neighbour estimate uses them (wn: 0 where censored or on
    the dark side of an edge); ``estimate`` and ``information``: L^ and 1 / variance of the window's result
    before step 4; ``candidates``: bool, where the result cannot tell the level from 0 (:func:`_candidates`),
    ``count`` of them."""

    weights: np.ndarray
    estimate: np.ndarray
    information: np.ndarray
    candidates: np.ndarray
    count: int

    def rows(self, keep: slice) -> Dark:
        """The arrays' rows ``keep``, ``count`` as it is: a strip's Dark (adaptive._solve) counts only the
        candidates of the rows it keeps, and those are ``keep``."""
        return Dark(self.weights[keep], self.estimate[keep], self.information[keep], self.candidates[keep],
                    self.count)


def joined(pieces: list[np.ndarray | None]) -> np.ndarray | None:
    """The strips' pieces one below the other (the piece itself when there is one; None when they are None)."""
    if pieces[0] is None:
        return None
    return pieces[0] if len(pieces) == 1 else np.concatenate(pieces)


def _wide_reach(ky: np.ndarray, kx: np.ndarray) -> tuple[int, int]:
    """(rows, columns) the wide fallback reads beyond a pixel: the widest scale's blocks, one block away, and half
    a block beyond their centres."""
    by, bx = len(ky) * 3 ** max(WIDE_SCALES - 1, 0), len(kx) * 3 ** max(WIDE_SCALES - 1, 0)
    return by + by // 2, bx + bx // 2


class WeightRows(NamedTuple):
    """The strips' weights (Dark.weights: views of it) as rows of one array, which the direct sums read in place.

    Attributes:
        rows: float32 (N, W), every strip's computed rows, one strip after the other.
        first: the row of ``rows`` holding each strip's first kept row (one a strip, in the order of the spans).
    """

    rows: np.ndarray
    first: list[int]


def wide_fallback(inp: SveInput, spans: list[tuple[int, int, int, int]], darks: list[Dark], image: np.ndarray,
                   variance: np.ndarray | None, ky: np.ndarray, kx: np.ndarray, workers: int | Executor,
                   pool: WeightRows | None = None) -> None:
    """Where a pixel's result cannot tell its level from 0, the levels of wider windows that are flat within their
    noise, scale by scale; ``image`` (and ``variance``) in place, float32 (H, W).

    A 3x3 window cannot tell a level far below its noise from 0, and step 4's
    answer there (about half the estimate's deviation) lies far above a level
    many stops lower. At scale j the eight blocks of (window x 3^j) around the
    pixel, one block away (so they hold none of the readings of its current
    estimate), give a neighbour level m = sum X_b / sum W_b (W_b, X_b: the
    block's sums of w and w x, the weights of step 1) with variance
    1 / sum W_b, if the region is flat. Whether it is, is the blocks' own
    evidence: under a constant level chi2 = sum W_b (X_b / W_b - m)^2 is
    chi-square with (blocks - 1) degrees of freedom; its excess over that,
    shrunk by CONTRAST_SIGMA of its standard errors (sqrt(2 dof)), over
    sum W_b is the squared bias b^2 of m, as step 2's is of the window's
    (bright structure a block away makes it large, and m counts for little).
    The pixel's estimate and m are then blended as in step 3 (information
    adds: t + 1 / (1 / sum W_b + b^2)), and the next scale (blocks three times
    larger around the blocks used) follows only where the blend still cannot
    tell the level from 0 and the blocks showed no structure (b^2 = 0). A block
    holding a censored reading (a level at least its bound, far above) stops
    the pixel at the scale before, as does a frame too small for the scale's
    blocks. Readings at the raw range's bottom count as what they read, as in
    steps 1-3. Step 4 is then applied to the new estimate.

    Cost: only strips holding such pixels, over their rows and as far as the
    widest blocks reach. Where they are many, each scale's block sums are two
    box filters over those rows (a row's pixels then computed whole, or, where
    few of the row's are active, gathered first: :func:`_wide_boxes`), the
    larger scales' made from the last scale's (:func:`_threefold`: a block is
    the 3 x 3 blocks of the scale before, added in float32); where few (fewer
    than one in WIDE_DIRECT times a block's pixels), each pixel sums its blocks'
    readings itself, in the same order. Where the first scale takes box filters
    and the band holds censored readings, the pixels one of whose blocks holds
    one (which that scale leaves unchanged) are left out first
    (:func:`_unheld`), so that a band whose pixels all lie beside saturation
    takes no block sums at all; the direct sums test a pixel's blocks for a
    censored reading before they sum them.

    ``pool``: where the strips' weights are rows of one array (:class:`WeightRows`), the direct sums read them
    there (a band's rows by an index) instead of a copy of the band's rows joined (0.1-0.2 ms a band); the box
    filters take the joined copy either way. None: the band's rows joined.
    """
    h, width = inp.shape
    reach = _wide_reach(ky, kx)
    none, none_held = np.empty((0, 0), np.float32), np.empty((0, 0), bool)

    def band(group: range) -> None:
        members = [i for i in group if darks[i].count]
        if not members:
            return
        top, end = spans[members[0]][1], spans[members[-1]][2]
        r0, r1 = max(top - reach[0], 0), min(end + reach[0], h)
        pieces = [(i, max(r0 - t, 0), max(min(r1, e) - t, 0)) for i, (_, t, e, _) in enumerate(spans)
                  if t < r1 and e > r0]  # each strip's rows in the band
        weights = None  # the band's rows joined, made where needed (always without a pool)
        if pool is None:
            weights = joined([darks[i].weights[a:b] for i, a, b in pieces])
            rows_of, row_index = weights, np.arange(r1 - r0)
        else:  # the direct sums' rows: the band's row r is row row_index[r] of pool.rows
            rows_of, row_index = pool.rows, np.concatenate([np.arange(pool.first[i] + a, pool.first[i] + b)
                                                            for i, a, b in pieces])
        size = (r1 - r0) * width
        signal, exposure, censored = inp.signal[r0:r1], inp.exposure[r0:r1], inp.censored[r0:r1]
        active = {i: darks[i].candidates.copy() for i in members}
        changed = {i: np.zeros_like(active[i]) for i in members}
        count, by, bx = sum(darks[i].count for i in members), len(ky), len(kx)
        # a pixel one of whose blocks holds a censored reading stops at the first scale unchanged: where that scale
        # takes box filters (and so makes these flags anyway), left out before any block sums (a band whose pixels
        # all lie beside saturation ends here)
        held_first, flagged = None, bool(censored.any())
        if count * by * bx * WIDE_DIRECT > size and flagged:
            held_first = _held(censored, by, bx)
            count = sum(_unheld(held_first, spans[i][1] - r0, by, bx, active[i]) for i in members)
            if count == 0:
                return
        helds = {0: held_first} if held_first is not None else {}

        def held_of(scale: int) -> np.ndarray:
            """The scale's blocks holding a censored reading (:func:`_held`; the censoring itself, unused, where the
            band holds none)."""
            if not flagged:
                return censored
            if scale not in helds:
                helds[scale] = _held(censored, len(ky) * 3**scale, len(kx) * 3**scale)
            return helds[scale]

        # box_w, box_wx: the blocks' sums of w and w x, of the scale `level` (made at the first scale that takes
        # box filters); a larger scale's from the last one's, three by three; `means` the scale's levels
        box_w, box_wx, means, level, scratch = None, None, None, 0, None
        for scale in range(WIDE_SCALES):
            if 3 * by > h or 3 * bx > width:
                break
            boxes = count * by * bx * WIDE_DIRECT > size  # many: box filters over the rows
            if boxes:
                if box_w is None:  # `means` holds w x until its sums are made
                    if weights is None:
                        weights = joined([darks[i].weights[a:b] for i, a, b in pieces])
                    means = np.empty_like(weights)
                    _wide_prepare(*flat(weights, signal, exposure, means))
                    box_w, box_wx, level = _box(weights, len(ky), len(kx)), _box(means, len(ky), len(kx)), 0
                scratch = np.empty_like(weights) if scratch is None and scale > level else scratch
                for smaller in range(level, scale):  # a block three times as large: the 3 x 3 of the last scale
                    steps = (len(ky) * 3**smaller, len(kx) * 3**smaller)
                    _threefold(box_wx, *steps, scratch)
                    _threefold(box_w, *steps, scratch)
                level = scale
                _block_means(*flat(box_w, box_wx, held_of(scale), means), flagged)
            count = 0
            for i in members:
                d, offset = darks[i], spans[i][1] - r0
                count += (_wide_boxes(box_w, means, offset, by, bx, active[i], changed[i], d.estimate,
                                      d.information) if boxes else
                          _wide_direct(rows_of, row_index, signal, exposure, censored if flagged else none_held,
                                       helds.get(scale, none_held), offset, len(ky), len(kx), 3**scale, active[i],
                                       changed[i], d.estimate, d.information))
            if count == 0:
                break
            by, bx = 3 * by, 3 * bx
        for i in members:
            rows = slice(*spans[i][1:3])
            posterior_at(changed[i], darks[i].estimate, darks[i].information, image[rows], posterior_polynomial(),
                          none if variance is None else variance[rows])

    groups = [range(i, min(i + WIDE_GROUP, len(spans))) for i in range(0, len(spans), WIDE_GROUP)]
    map_on(workers, band, groups)


def _box(a: np.ndarray, by: int, bx: int) -> np.ndarray:
    """Sums of ``a`` (float32 (H, W)) over the by x bx box around each pixel, borders reflect-101."""
    return cv2.boxFilter(a, cv2.CV_32F, (bx, by), normalize=False, borderType=cv2.BORDER_REFLECT_101)


def _threefold(a: np.ndarray, oy: int, ox: int, scratch: np.ndarray) -> None:
    """``a`` (float32 (H, W): a box filter's sums, borders reflect-101) in place = its sums at the 3 x 3 pixels
    ``oy`` rows and ``ox`` columns apart around each pixel, reflect-101 (``scratch``: an array like ``a``). Where
    ``a`` holds the sums of oy x ox boxes, those of the 3 oy x 3 ox boxes (:func:`_box`): the same readings (a
    box's sums over the reflected array are even about its ends, as the array is), in float32 rounding instead of
    OpenCV's float64 sums (a relative difference of a few 1e-7)."""
    _threefold_rows(a, ox, scratch)
    _threefold_columns(scratch, oy, a)


@kernel
def _threefold_rows(a, ox, out):
    """out[:, c] = a[:, c - ox] + a[:, c] + a[:, c + ox], columns reflect-101; the middle as vectorised loops."""
    h, width = a.shape
    inner = width - 2 * ox
    for r in range(h):
        row, target = a[r], out[r]
        for c in range(min(ox, width)):
            target[c] = row[reflect_101(c - ox, width)] + row[c] + row[reflect_101(c + ox, width)]
        for c in range(max(width - ox, ox), width):
            target[c] = row[reflect_101(c - ox, width)] + row[c] + row[reflect_101(c + ox, width)]
        if inner > 0:
            left, centre, right = row[:inner], row[ox:ox + inner], row[2 * ox:2 * ox + inner]
            middle = target[ox:ox + inner]
            for i in range(inner):
                middle[i] = left[i] + centre[i] + right[i]


@kernel
def _threefold_columns(a, oy, out):
    """out[r] = a[r - oy] + a[r] + a[r + oy], rows reflect-101, as vectorised loops."""
    h, width = a.shape
    for r in range(h):
        above, centre, below, target = a[reflect_101(r - oy, h)], a[r], a[reflect_101(r + oy, h)], out[r]
        for c in range(width):
            target[c] = above[c] + centre[c] + below[c]


def _held(censored: np.ndarray, by: int, bx: int) -> np.ndarray:
    """Where the by x bx box around a pixel holds a censored reading: bool (H, W) of ``censored`` (bool (H, W)),
    borders reflect-101 (the boxes of :func:`_box`)."""
    return cv2.dilate(censored.view(np.uint8), np.ones((by, bx), np.uint8),
                      borderType=cv2.BORDER_REFLECT_101).view(bool)


@kernel
def _unheld(held, offset, by, bx, active):
    """active = False, in place, where one of a pixel's eight blocks (by x bx, one block away; reflect-101) holds a
    censored reading (``held``: :func:`_held` of the band; row r of ``active``, bool (R, W), is row r + offset of
    it), as :func:`_wide_blend` stops such a pixel; the number left active. A row's middle as vectorised loops."""
    h, width = held.shape
    inner = width - 2 * bx
    ends = min(bx, width)  # the row's ends, whose blocks reflect: [0, ends) and [max(width - bx, ends), width)
    left_active = 0
    for r in range(active.shape[0]):
        row = active[r]
        if count_true(row) == 0:
            continue
        br = r + offset
        above, centre, below = held[reflect_101(br - by, h)], held[br], held[reflect_101(br + by, h)]
        for i in range(ends + width - max(width - bx, ends)):
            c = i if i < ends else max(width - bx, ends) + i - ends
            row[c] = row[c] and not _held_near(held, br, c, by, bx)
        if inner > 0:  # as bytes, the blocks' rows shifted, which LLVM vectorises
            middle, two = row[bx:bx + inner].view(np.uint8), 2 * bx
            up, mid, down = above.view(np.uint8), centre.view(np.uint8), below.view(np.uint8)
            a0, a1, a2 = up[:inner], up[bx:bx + inner], up[two:two + inner]
            b0, b2 = mid[:inner], mid[two:two + inner]
            c0, c1, c2 = down[:inner], down[bx:bx + inner], down[two:two + inner]
            for i in range(inner):
                middle[i] = middle[i] & ~(a0[i] | a1[i] | a2[i] | b0[i] | b2[i] | c0[i] | c1[i] | c2[i])
        left_active += count_true(row)
    return left_active


@kernel
def _wide_prepare(weights, signal, exposure, weighted):
    """weighted = w x (x = s / e); flat arrays."""
    for k in range(weights.size):
        weighted[k] = weights[k] * (signal[k] / exposure[k])


@kernel
def _block_means(box_w, box_wx, held, means, flagged):
    """means = the blocks' levels X / W (0 where a block holds no reading: W <= TINY), NaN where a block holds a
    censored reading (``held``, if ``flagged``); flat float32 arrays (``held`` bool)."""
    tiny, nan = np.float32(TINY), np.float32(np.nan)
    for k in range(box_w.size):
        w = box_w[k]
        level = box_wx[k] / max(w, tiny) if w > tiny else np.float32(0.0)
        means[k] = nan if flagged and held[k] else level


@kernel
def _block(w, level):
    """A block's (W, W m, 1) where it holds readings (W > TINY), else zeros; float32."""
    zero, one = np.float32(0.0), np.float32(1.0)
    valid = w > np.float32(TINY)
    return (w if valid else zero), (w * level if valid else zero), (one if valid else zero)


@kernel
def _deviation(w, level, mean):
    """W (m - mean)^2 of a block holding readings, else 0; float32."""
    d = level - mean
    return w * d * d if w > np.float32(TINY) else np.float32(0.0)


@kernel
def _wide_blend(block_w, block_m, r, c, active, changed, estimate, information):
    """The blend of one scale of :func:`wide_fallback` at pixel (r, c) from its eight blocks (float32 (8,): W and
    the level m = X / W, NaN where flagged); whether the next scale follows. The same arithmetic, in the same order,
    as :func:`_wide_row` (bit for bit)."""
    zero = np.float32(0.0)
    sum_w, sum_wx, blocks, bad = zero, zero, zero, False
    for b in range(8):
        a, x, k = _block(block_w[b], block_m[b])
        sum_w += a
        sum_wx += x
        blocks += k
        bad |= block_m[b] != block_m[b]
    mean = sum_wx / max(sum_w, np.float32(TINY))
    chi2 = zero
    for b in range(8):
        chi2 += _deviation(block_w[b], block_m[b], mean)
    if bad or blocks < np.float32(2.0):
        active[r, c] = False
        return False
    value, t, keep = _wide_step(estimate[r, c], information[r, c], sum_w, mean, chi2, blocks)
    estimate[r, c] = value
    information[r, c] = t
    changed[r, c] = True
    active[r, c] = keep
    return keep


@kernel
def _wide_step(estimate, information, sum_w, level, chi2, blocks):
    """(estimate, information, whether the next scale follows) after blending in a scale's neighbour level
    (:func:`wide_fallback`), float32."""
    zero, one, two = np.float32(0.0), np.float32(1.0), np.float32(2.0)
    sigmas = np.float32(CONTRAST_SIGMA)
    dof = blocks - one
    bias2 = max(chi2 - dof - sigmas * np.sqrt(two * dof), zero) / sum_w
    weight = one / (one / sum_w + bias2)
    t = information + weight
    value = (estimate * information + level * weight) / t
    keep = (bias2 <= zero) & ((value <= zero) | (value * value * t < sigmas * sigmas))
    return value, t, keep


@kernel
def _wide_boxes(box_w, means, offset, by, bx, active, changed, estimate, information):
    """One scale of :func:`wide_fallback` at the ``active`` pixels of a strip's rows (bool (R, W); row r of the
    strip is row r + offset of the band's block sums ``box_w`` and levels ``means`` (:func:`_block_means`), blocks
    by x bx); the number of pixels the next scale follows at. A row with many active pixels (more than one in
    WIDE_DENSE_ROW) is computed whole away from its ends (:func:`_wide_row`, vectorised) and its ends pixel by
    pixel; a row with fewer has its active pixels' blocks gathered into short arrays first (:func:`_wide_packed`);
    all alike bit for bit."""
    h, width = box_w.shape
    rows, cols = np.empty(3, np.int64), np.empty(3, np.int64)
    block_w, block_m = np.empty(8, np.float32), np.empty(8, np.float32)
    index, blocks = np.empty((3, width), np.int64), np.empty((16, width), np.float32)
    packed_active, packed_changed = np.empty(width, np.bool_), np.empty(width, np.bool_)
    packed_estimate, packed_information = np.empty(width, np.float32), np.empty(width, np.float32)
    inner = width - 2 * bx
    kept = 0
    for r in range(active.shape[0]):
        br = r + offset
        n = count_true(active[r])
        if n == 0:
            continue
        for i in range(3):
            rows[i] = reflect_101(br + (i - 1) * by, h)
        if not (n * WIDE_DENSE_ROW > width and inner > 0):
            kept += _wide_packed(box_w, means, rows, bx, n, active[r], changed[r], estimate[r], information[r],
                                 index, blocks, packed_active, packed_changed, packed_estimate, packed_information)
            continue
        kept += _wide_row(box_w, means, rows, bx, active[r, bx:bx + inner], changed[r, bx:bx + inner],
                          estimate[r, bx:bx + inner], information[r, bx:bx + inner])
        for k in range(2 * bx):  # the row's ends
            c = k if k < bx else k + inner
            if not active[r, c]:
                continue
            for i in range(3):
                cols[i] = reflect_101(c + (i - 1) * bx, width)
            b = 0
            for i in range(3):
                for j in range(3):
                    if i == 1 and j == 1:
                        continue
                    block_w[b], block_m[b] = box_w[rows[i], cols[j]], means[rows[i], cols[j]]
                    b += 1
            kept += _wide_blend(block_w, block_m, r, c, active, changed, estimate, information)
    return kept


#: :func:`_wide_boxes` computes a row whole (every pixel, vectorised) where more than one pixel in this many is
#: active, else gathers the active pixels' blocks first (:func:`_wide_packed`).
WIDE_DENSE_ROW = 32


@kernel
def _wide_packed(box_w, means, rows, bx, count, active, changed, estimate, information, index, blocks,
                 packed_active, packed_changed, packed_estimate, packed_information):
    """:func:`_wide_row` at the active pixels of a whole row (``active``, ``changed``, ``estimate`` and
    ``information``: the row, in place; ``rows``: the band rows of its blocks; ``count``: its active pixels) packed:
    their columns into ``index[1]`` (base.true_positions; int64 (3, W): their blocks' columns a block left and
    right into rows 0 and 2), their eight blocks' W and levels into ``blocks`` (float32 (16, W): W of blocks 0-7,
    then their levels), a block at a time (the pixels' reads from one band row, in order: x0.87 of a pixel's 16 at
    a time on StarField 1/1/8/8 bright's packed rows), and their values into the ``packed_*`` scratch rows,
    :func:`_wide_lanes` on those, then scattered back; the number kept active."""
    width = active.size
    n = true_positions(active, count, index[1])
    for j in range(n):
        c = index[1, j]
        index[0, j], index[2, j] = reflect_101(c - bx, width), reflect_101(c + bx, width)
        packed_active[j], packed_changed[j] = True, changed[c]
        packed_estimate[j], packed_information[j] = estimate[c], information[c]
    b = 0
    for i in range(3):
        row_w, row_m = box_w[rows[i]], means[rows[i]]
        for k in range(3):
            if i == 1 and k == 1:
                continue
            cols, out_w, out_m = index[k], blocks[b], blocks[8 + b]
            for j in range(n):
                out_w[j], out_m[j] = row_w[cols[j]], row_m[cols[j]]
            b += 1
    kept = _wide_lanes(blocks[0, :n], blocks[1, :n], blocks[2, :n], blocks[3, :n], blocks[4, :n], blocks[5, :n],
                       blocks[6, :n], blocks[7, :n], blocks[8, :n], blocks[9, :n], blocks[10, :n], blocks[11, :n],
                       blocks[12, :n], blocks[13, :n], blocks[14, :n], blocks[15, :n], packed_active[:n],
                       packed_changed[:n], packed_estimate[:n], packed_information[:n])
    for j in range(n):
        c = index[1, j]
        active[c], changed[c] = packed_active[j], packed_changed[j]
        estimate[c], information[c] = packed_estimate[j], packed_information[j]
    return kept


@kernel
def _wide_row(box_w, means, rows, bx, active, changed, estimate, information):
    """:func:`_wide_blend` at every pixel of a row away from its ends (columns bx .. W - bx: ``active``,
    ``changed``, ``estimate`` and ``information`` are that part of the row): :func:`_wide_lanes` on the blocks'
    rows of ``box_w`` and ``means`` shifted by a block; the number of pixels kept active."""
    n = active.size
    two = 2 * bx
    r0, r1, r2 = rows[0], rows[1], rows[2]
    return _wide_lanes(box_w[r0, :n], box_w[r0, bx:bx + n], box_w[r0, two:two + n], box_w[r1, :n],
                       box_w[r1, two:two + n], box_w[r2, :n], box_w[r2, bx:bx + n], box_w[r2, two:two + n],
                       means[r0, :n], means[r0, bx:bx + n], means[r0, two:two + n], means[r1, :n],
                       means[r1, two:two + n], means[r2, :n], means[r2, bx:bx + n], means[r2, two:two + n],
                       active, changed, estimate, information)


@kernel
def _wide_lanes(w0, w1, w2, w3, w4, w5, w6, w7, m0, m1, m2, m3, m4, m5, m6, m7, active, changed, estimate,
                information):
    """:func:`_wide_blend` at N pixels at once from their eight blocks' W (``w0`` .. ``w7``) and levels (``m0`` ..
    ``m7``, NaN where flagged; float32 (N,), the blocks in :func:`_wide_blend`'s order), in one loop that LLVM
    vectorises, with the same arithmetic in the same order; ``active``, ``changed``, ``estimate`` and
    ``information`` (N,) in place; the number of pixels kept active."""
    n = active.size
    zero, tiny, two_blocks = np.float32(0.0), np.float32(TINY), np.float32(2.0)
    for c in range(n):
        a0, b0, n0 = _block(w0[c], m0[c])
        a1, b1, n1 = _block(w1[c], m1[c])
        a2, b2, n2 = _block(w2[c], m2[c])
        a3, b3, n3 = _block(w3[c], m3[c])
        a4, b4, n4 = _block(w4[c], m4[c])
        a5, b5, n5 = _block(w5[c], m5[c])
        a6, b6, n6 = _block(w6[c], m6[c])
        a7, b7, n7 = _block(w7[c], m7[c])
        bad = ((m0[c] != m0[c]) | (m1[c] != m1[c]) | (m2[c] != m2[c]) | (m3[c] != m3[c]) | (m4[c] != m4[c])
               | (m5[c] != m5[c]) | (m6[c] != m6[c]) | (m7[c] != m7[c]))
        sum_w = zero + a0 + a1 + a2 + a3 + a4 + a5 + a6 + a7
        sum_wx = zero + b0 + b1 + b2 + b3 + b4 + b5 + b6 + b7
        blocks = zero + n0 + n1 + n2 + n3 + n4 + n5 + n6 + n7
        mean = sum_wx / max(sum_w, tiny)
        chi2 = (zero + _deviation(w0[c], m0[c], mean) + _deviation(w1[c], m1[c], mean)
                + _deviation(w2[c], m2[c], mean) + _deviation(w3[c], m3[c], mean)
                + _deviation(w4[c], m4[c], mean) + _deviation(w5[c], m5[c], mean)
                + _deviation(w6[c], m6[c], mean) + _deviation(w7[c], m7[c], mean))
        go = active[c] & ~bad & (blocks >= two_blocks)
        value, t, keep = _wide_step(estimate[c], information[c], sum_w, mean, chi2, blocks)
        estimate[c] = value if go else estimate[c]
        information[c] = t if go else information[c]
        changed[c] |= go
        active[c] = go & keep
    return count_true(active)  # counted apart: a count inside the loop above keeps LLVM from vectorising it


@kernel
def _wide_direct(weights, weight_rows, signal, exposure, censored, held, offset, ky, kx, blocks, active, changed,
                 estimate, information):
    """:func:`_wide_boxes` with each active pixel summing its blocks' readings itself (few active pixels): the
    band's weights (its row r: row ``weight_rows[r]`` of ``weights``, int64 (H,)), signals, exposures and
    censoring (of no rows where none is censored), and the scale's blocks holding a censored reading (``held``,
    :func:`_held`) where made, else of no rows (row r of ``active`` is row r + offset of them). The scale's blocks
    are ``blocks`` x ``blocks`` windows (``ky`` x ``kx`` readings) each:
    each window's sums in float64, its readings added row by row (:func:`_window_sums`), then the windows' sums
    added three by three along rows, then down columns, in float32, as :func:`_threefold` adds the box filters'
    (the same additions; yet with WIDE_DIRECT changed, 5 of the 42 bench frames' images change, so the choice of
    path is part of the result: docs/benchmarks.md, worst89); a pixel one of whose blocks holds a censored reading
    stops before any sums (found in ``held``, else in its blocks' readings). A row's active pixels are found by
    base.true_positions (rows without any skipped at a count)."""
    h, width = signal.shape
    tiny = np.float32(TINY)
    by, bx = ky * blocks, kx * blocks
    grid = 3 * blocks  # the windows across (and down) a pixel's eight blocks and itself
    block_w, block_m = np.empty(8, np.float32), np.empty(8, np.float32)
    window_w, window_x = np.empty((grid, grid), np.float32), np.empty((grid, grid), np.float32)
    sums_w, sums_x = np.empty((blocks, blocks), np.float32), np.empty((blocks, blocks), np.float32)
    index = np.empty(width, np.int64)
    kept = 0
    for r in range(active.shape[0]):
        row = active[r]
        n = count_true(row)
        if n == 0:
            continue
        n = true_positions(row, n, index)
        br = r + offset
        for j in range(n):  # a pixel changes only its own flags: the columns found first are those visited
            c = index[j]
            if (_held_near(held, br, c, by, bx) if held.shape[0] > 0 else
                    censored.shape[0] > 0 and _censored_near(censored, br, c, by, bx)):
                active[r, c] = False  # it stops unchanged, as _wide_blend stops it
                continue
            for gy in range(grid):
                top = br - by - by // 2 + gy * ky
                for t in range(blocks):  # three windows side by side at a time: a block's row of them at scale > 0
                    if blocks > 1 and gy // blocks == 1 and t == 1:
                        continue  # the pixel's own block
                    w0, w1, w2, x0, x1, x2 = _window_sums(weights, weight_rows, signal, exposure, top,
                                                          c - bx - bx // 2 + 3 * t * kx, ky, kx)
                    k = 3 * t
                    window_w[gy, k], window_w[gy, k + 1], window_w[gy, k + 2] = (np.float32(w0), np.float32(w1),
                                                                                 np.float32(w2))
                    window_x[gy, k], window_x[gy, k + 1], window_x[gy, k + 2] = (np.float32(x0), np.float32(x1),
                                                                                 np.float32(x2))
            for i in range(9):
                if i == 4:
                    continue
                bi, bj = (i // 3) * blocks, (i % 3) * blocks
                if blocks == 1:
                    w32, x32 = window_w[bi, bj], window_x[bi, bj]
                else:
                    for a in range(blocks):
                        for b in range(blocks):
                            sums_w[a, b], sums_x[a, b] = window_w[bi + a, bj + b], window_x[bi + a, bj + b]
                    _threefold_block(sums_w)
                    _threefold_block(sums_x)
                    w32, x32 = sums_w[0, 0], sums_x[0, 0]
                b = i if i < 4 else i - 1
                block_w[b] = w32
                block_m[b] = x32 / max(w32, tiny) if w32 > tiny else np.float32(0.0)
            kept += _wide_blend(block_w, block_m, r, c, active, changed, estimate, information)
    return kept


@kernel
def _window_sums(weights, weight_rows, signal, exposure, top, left, ky, kx):
    """The float64 sums (W0, W1, W2, X0, X1, X2) of w and w x (x = s / e) over three ky x kx windows side by side
    (their first row ``top``, first columns ``left``, ``left + kx``, ``left + 2 kx``) of the band's (H, W)
    arrays (its weights' row r: row ``weight_rows[r]`` of ``weights``), borders reflect-101; each window's readings
    added row by row from 0, the three windows' additions
    interleaved (the direct calls of the 42 bench frames, recorded: x0.74 of one window summed at a time)."""
    h, width = signal.shape
    w0, w1, w2, x0, x1, x2 = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    for dy in range(ky):
        rr = reflect_101(top + dy, h)
        wr, sr, er = weights[weight_rows[rr]], signal[rr], exposure[rr]
        for dx in range(kx):
            c0 = reflect_101(left + dx, width)
            c1 = reflect_101(left + kx + dx, width)
            c2 = reflect_101(left + 2 * kx + dx, width)
            a, b, c = wr[c0], wr[c1], wr[c2]
            w0 += a
            x0 += a * (sr[c0] / er[c0])
            w1 += b
            x1 += b * (sr[c1] / er[c1])
            w2 += c
            x2 += c * (sr[c2] / er[c2])
    return w0, w1, w2, x0, x1, x2


@kernel
def _censored_near(censored, r, c, by, bx):
    """Whether one of the eight by x bx blocks one block away from pixel (r, c) of ``censored`` (bool (H, W))
    holds a censored reading, borders reflect-101 (the first one found ends the search)."""
    h, width = censored.shape
    for i in range(9):
        if i == 4:
            continue
        top, left = r + (i // 3 - 1) * by - by // 2, c + (i % 3 - 1) * bx - bx // 2
        for dy in range(by):
            row = censored[reflect_101(top + dy, h)]
            for dx in range(bx):
                if row[reflect_101(left + dx, width)]:
                    return True
    return False


@kernel
def _held_near(held, r, c, by, bx):
    """Whether one of the eight blocks one block (by x bx) away from pixel (r, c) holds a censored reading
    (``held``: :func:`_held`), borders reflect-101."""
    h, width = held.shape
    rows = (reflect_101(r - by, h), r, reflect_101(r + by, h))
    cols = (reflect_101(c - bx, width), c, reflect_101(c + bx, width))
    return (held[rows[0], cols[0]] or held[rows[0], cols[1]] or held[rows[0], cols[2]] or held[rows[1], cols[0]]
            or held[rows[1], cols[2]] or held[rows[2], cols[0]] or held[rows[2], cols[1]] or held[rows[2], cols[2]])


@kernel
def _threefold_block(sums):
    """sums[0, 0] = the sum of the square float32 ``sums`` (3^k x 3^k), three by three along rows, then down
    columns, level by level, in :func:`_threefold`'s order; ``sums`` is scratch."""
    n = sums.shape[0]
    while n > 1:
        for a in range(n):
            for b in range(n // 3):
                sums[a, b] = sums[a, 3 * b] + sums[a, 3 * b + 1] + sums[a, 3 * b + 2]
        for a in range(n // 3):
            for b in range(n // 3):
                sums[a, b] = sums[3 * a, b] + sums[3 * a + 1, b] + sums[3 * a + 2, b]
        n //= 3
