"""The chroma's cells (svelive.reconstruction.colour, step a): their layout, which the pattern and the CFA
alone fix (:func:`cell_layout`), and each cell's statistics of its readings per channel, in one compiled
pass over the pixels (:func:`_cell_stats`)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from svelive.core.cfa import ColourFilter, joint_period
from svelive.core.pattern import Pattern
from svelive.jit import kernel


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
    for i in range(mean.shape[1]):
        _cell_stats_row(values, censored, channels, levels, exposures, per_pixel, gain_inv, floor, censor, mean, info,
                        kept, weighted_mean, bound, flags, sums, scratch, i, i)


@kernel
def _cell_stats_row(values, censored, channels, levels, exposures, per_pixel, gain_inv, floor, censor,
                    mean, info, kept, weighted_mean, bound, flags, sums, scratch, i, o):
    """:func:`_cell_stats` of cell row ``i`` into row ``o`` of its outputs (whole planes, ``o`` = ``i``, or rings of
    cell rows: svelive.reconstruction.colour.shares._chroma_pass)."""
    h, w = values.shape
    cy, cx = channels.shape
    zero, one = np.float32(0.0), np.float32(1.0)
    x_sum, n_sum, all_sum = sums[0], sums[1], sums[2]
    r0, r1 = i * cy, min(i * cy + cy, h)
    sums[...] = zero
    # the cells of common widths spelt out: loops whose loads LLVM vectorises; every cell of the row is whole there, so
    # the count of all readings is the same in each: counted in the first cell's and copied to the others after
    spelt = (cx == 2 or cx == 4) and w % cx == 0
    for r in range(r0, r1):
        ch, k, row, lost = channels[r - r0], levels[r - r0], values[r], censored[r]
        if cx == 2 and spelt:
            _add_pairs(row, lost, x_sum[ch[0], k[0]], n_sum[ch[0], k[0]], x_sum[ch[1], k[1]], n_sum[ch[1], k[1]])
            all_sum[ch[0], k[0], 0] += one
            all_sum[ch[1], k[1], 0] += one
            continue
        if cx == 4 and spelt:
            for half in range(2):
                a, b = 2 * half, 2 * half + 1
                _add_pairs_of_four(row, lost, half, x_sum[ch[a], k[a]], n_sum[ch[a], k[a]], x_sum[ch[b], k[b]],
                                   n_sum[ch[b], k[b]])
                all_sum[ch[a], k[a], 0] += one
                all_sum[ch[b], k[b], 0] += one
            continue
        for px in range(min(cx, w)):
            xs, ns, alls = x_sum[ch[px], k[px]], n_sum[ch[px], k[px]], all_sum[ch[px], k[px]]
            for j in range((w - px + cx - 1) // cx):
                keep = zero if lost[j * cx + px] else one
                xs[j] += row[j * cx + px] * keep
                ns[j] += keep
                alls[j] += one
    if spelt:
        for c in range(3):
            for level in range(exposures.size):
                alls = all_sum[c, level]
                for j in range(1, alls.size):
                    alls[j] = alls[0]
    flags[:, o, :] = 0
    if exposures.size == 2:  # (dual-ISO, quad- and column-Bayer: one loop a channel, 1.1 ms less a 1920x1200 frame)
        for ch in range(3):
            _channel_two_levels(x_sum[ch, 0], n_sum[ch, 0], all_sum[ch, 0], x_sum[ch, 1], n_sum[ch, 1],
                                all_sum[ch, 1], exposures[0], exposures[1], per_pixel, gain_inv, floor, censor,
                                mean[ch, o], info[ch, o], kept[ch, o], weighted_mean[ch, o], bound[ch, o], flags[0, o],
                                flags[1, o])
        return
    for ch in range(3):  # per channel, loops over the cells of the row (which vectorise)
        s_total, e_total, pilot = scratch[0], scratch[1], scratch[2]
        weighted, total, full = scratch[3], scratch[4], scratch[5]
        b = bound[ch, o]
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
        m, n, kp, km = mean[ch, o], info[ch, o], kept[ch, o], weighted_mean[ch, o]
        for j in range(m.size):
            ok = total[j] > zero
            m[j] = weighted[j] / total[j] if ok else zero
            n[j] = total[j]
            kp[j] = total[j] / full[j] if ok else zero
            km[j] = weighted[j] / full[j] if ok else zero
        clipped, lost = flags[0, o], flags[1, o]
        for j in range(m.size):
            some = b[j] > zero
            clipped[j] |= np.uint8(some and total[j] <= zero)
            lost[j] |= np.uint8(some)


@kernel
def _channel_two_levels(xs0, ns0, alls0, xs1, ns1, alls1, e0, e1, per_pixel, gain_inv, floor, censor, m, n, kp, km, b,
                        clipped, lost):
    """:func:`_cell_stats_row`'s per-cell stage for one channel of a pattern of two exposure levels ``e0`` and ``e1``,
    from the sums of each level's readings (values ``xs``, uncensored ``ns``, all ``alls``; float32 (Wc,) each) into
    the cell row's ``m`` (mean), ``n`` (info), ``kp`` (kept), ``km`` (weighted mean), ``b`` (bound) and the flags'
    rows ``clipped`` and ``lost`` (uint8, or-ed into): the general loops' operations in their order, in one loop
    whose values stay in registers instead of six scratch rows written and read again per level."""
    zero, one = np.float32(0.0), np.float32(1.0)
    inverse0 = one if per_pixel else one / e0
    inverse1 = one if per_pixel else one / e1
    bound0, bound1 = censor / e0, censor / e1
    for j in range(m.size):
        x0, x1 = xs0[j] * inverse0, xs1[j] * inverse1
        s_total = zero + x0 * e0
        s_total += x1 * e1
        e_total = zero + ns0[j] * e0
        e_total += ns1[j] * e1
        lb = max(max(zero, bound0 if alls0[j] > ns0[j] else zero), bound1 if alls1[j] > ns1[j] else zero)
        pilot = max(s_total / e_total, zero) * gain_inv if e_total > zero else zero
        w0 = e0 * e0 / (e0 * pilot + floor)
        w1 = e1 * e1 / (e1 * pilot + floor)
        weighted = zero + w0 * x0
        weighted += w1 * x1
        total = zero + w0 * ns0[j]
        total += w1 * ns1[j]
        full = zero + w0 * alls0[j]
        full += w1 * alls1[j]
        ok = total > zero
        m[j] = weighted / total if ok else zero
        n[j] = total
        kp[j] = total / full if ok else zero
        km[j] = weighted / full if ok else zero
        b[j] = lb
        some = lb > zero
        clipped[j] |= np.uint8(some and total <= zero)
        lost[j] |= np.uint8(some)


@kernel
def _add_pairs(row, lost, xs0, ns0, xs1, ns1):
    """Cells of 2 columns: the row's even pixels into the first sums (of the values and the uncensored count), odd
    ones into the second."""
    zero, one = np.float32(0.0), np.float32(1.0)
    for j in range(row.size // 2):
        keep0 = zero if lost[2 * j] else one
        keep1 = zero if lost[2 * j + 1] else one
        xs0[j] += row[2 * j] * keep0
        ns0[j] += keep0
        xs1[j] += row[2 * j + 1] * keep1
        ns1[j] += keep1


@kernel
def _add_pairs_of_four(row, lost, half, xs0, ns0, xs1, ns1):
    """Cells of 4 columns: pixels 2 half and 2 half + 1 of each into the first and second sums (as
    :func:`_add_pairs`)."""
    zero, one = np.float32(0.0), np.float32(1.0)
    a, b = 2 * half, 2 * half + 1
    for j in range(row.size // 4):
        keep0 = zero if lost[4 * j + a] else one
        keep1 = zero if lost[4 * j + b] else one
        xs0[j] += row[4 * j + a] * keep0
        ns0[j] += keep0
        xs1[j] += row[4 * j + b] * keep1
        ns1[j] += keep1
