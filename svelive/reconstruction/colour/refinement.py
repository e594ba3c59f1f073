"""The luminance refined at the chroma's scale (svelive.reconstruction.colour, step b'): moved towards the
cells' coarse luminance by a noise-model garrote where the two differ by no more than noise
(:func:`refine`)."""

from __future__ import annotations

from concurrent.futures import Executor

import numpy as np

from svelive.jit import kernel
from svelive.reconstruction.colour.folding import _colour_pixel, _finite_row
from svelive.reconstruction.colour.interpolate import Interpolation, _full_width, _pieces
from svelive.reconstruction.methods.base import map_on


def refine(luminance: np.ndarray, variance: np.ndarray, inter: Interpolation, cell: tuple[int, int], *,
           weight: np.ndarray | None = None, floor: np.ndarray | None = None, out: np.ndarray | None = None,
           out_variance: np.ndarray | None = None, new_variance: bool = False, rgb: np.ndarray | None = None,
           finite: np.ndarray | None = None, workers: int | Executor = 1) -> np.ndarray:
    """Move the luminance Y towards the coarse L where they differ by no more than noise.

    Y (the mono method's, variance v_Y) and L (the chroma cells', variance v_L; package
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
        floor: float32 (Hc, W) or None: where ``weight`` < 1, ``variance`` is at least the floor of the
            pixel's cell row at its column (a stream's measured noise, stream.luminance_noise); only with
            ``weight``, ``out`` None and a new ``out_variance`` (or none).
        out, out_variance: where to write the result and its variance (a new array, and not
            computed, when None).
        new_variance: ``out_variance`` is none of the inputs (with ``out`` None, both are
            written in one loop that vectorises, without a scratch row).
        rgb: float32 (H, W, 3) or None: where to write the refined Y coloured, Y k_c with the shares
            of ``inter`` (bit for bit folding.colourise of the result), each row while it is in cache;
            only with ``out`` None and a new ``out_variance`` (or none).
        finite: bool (H,) or None: with ``rgb``, each row's flag, set True where every value of its RGB row
            is finite, else False (checked while the row is in cache: single.run_method's guard).
        workers: threads for its pieces of rows (base.map_on); the result does not depend on it.

    Returns:
        ``out``, float32 (H, W).
    """
    (cy, cx), (h, w) = cell, luminance.shape
    hc, wc = inter.cells[0].shape[1], -(-w // cx)
    top, frac = inter.top, inter.frac

    def residual_cells(first: int, stop: int, coarse: np.ndarray, base: int, into: np.ndarray) -> None:
        # cell rows [first, stop) into ``into`` (rows, Wc), from ``coarse``: the coarse luminance's cell rows
        # from ``base`` on at every column
        rows = slice(first * cy, min(stop * cy, h))
        _residual_cells(luminance[rows], coarse, top[rows] - base, frac[rows], cy, cx, into,
                        np.empty((2, w), np.float32))

    none = np.empty((0, 0), np.float32)
    fresh_out = out is None and (out_variance is None or new_variance)
    if (rgb is not None or floor is not None) and not fresh_out:
        raise ValueError("refine writes rgb and takes a floor only into a new out (and a new out_variance or none)")
    if finite is not None and rgb is None:
        raise ValueError("refine checks the rgb it writes: finite needs rgb")
    if floor is not None and weight is None:
        raise ValueError("refine's floor applies where the weight is below 1: give the weight")
    if fresh_out:  # written in the loop (no scratch row: 40 % faster)
        out = np.empty((h, w), np.float32)
        interleaved = none if rgb is None else rgb.reshape(h, 3 * w)  # (H, 3 W): flat rows, as colourise's
        no_flags = np.empty(0, np.bool_)

        def fresh(rows: slice) -> None:
            # what these rows read, made here and read while in cache: the residual of the cell rows [a, b) they
            # lie between, and (unless made whole) the planes at every column on the cell rows that residual reads
            a, b = inter.cell_rows(rows)
            planes, c = inter.piece_rows(slice(a * cy, min(b * cy, h)))
            residual = np.empty((1, b - a, wc), np.float32)
            residual_cells(a, b, planes[3], c, residual[0])
            _refine_into(luminance[rows], variance[rows], none if weight is None else weight[rows],
                         none if floor is None else floor, rows.start, cy, planes[3], planes[4],
                         _full_width((residual,), cx, w)[0], a - c, top[rows] - c, frac[rows], out[rows],
                         none if out_variance is None else out_variance[rows], planes,
                         none if rgb is None else interleaved[rows], no_flags if finite is None else finite[rows])

        map_on(workers, fresh, _pieces(h))
        return out
    out = np.empty((h, w), np.float32) if out is None else out
    residual = np.empty((1, hc, wc), np.float32)  # every cell first: ``out`` may be the luminance
    map_on(workers, lambda rows: residual_cells(rows.start // cy, -(-rows.stop // cy), inter.rows[3], 0,
                                                residual[0, rows.start // cy:-(-rows.stop // cy)]), _pieces(h, cy))
    residual_rows = _full_width((residual,), cx, w)[0]

    def piece(rows: slice) -> None:
        _refine(luminance[rows], variance[rows], none if weight is None else weight[rows], inter.rows[3],
                inter.rows[4], residual_rows, top[rows], frac[rows], out[rows],
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
def _refine_into(luminance, variance, weight, floor, first, cy, coarse, coarse_variance, residual, residual_first, top,
                 frac, out, out_variance, planes, rgb, finite):
    """:func:`_refine` into ``out`` and ``out_variance`` (may be empty) that are none of the inputs:
    the same arithmetic per pixel, stored in the loop; ``residual``'s rows are those of the other planes
    from ``residual_first`` on; ``floor`` (Hc, W), unless empty: :func:`refine`'s, for rows from frame row
    ``first`` on, cells of ``cy`` rows. ``rgb`` (R, 3 W), unless empty: each
    row's result times the shares ``planes[0:3]`` (P, Hc, W) interpolated between its two cell rows,
    as folding._colourise, in the same loop; ``finite`` (R,) bool, unless empty: whether each RGB row is all
    finite."""
    weighted, with_variance, floored = weight.size > 0, out_variance.size > 0, floor.size > 0
    last = coarse.shape[0] - 1
    one = np.float32(1.0)
    for r in range(luminance.shape[0]):
        t0, f = top[r], frac[r]
        t1 = min(t0 + 1, last)
        l0, l1, v0, v1, e0, e1 = (coarse[t0], coarse[t1], coarse_variance[t0], coarse_variance[t1],
                                  residual[t0 - residual_first], residual[t1 - residual_first])
        y, vy, o = luminance[r], variance[r], out[r]
        wy = weight[r] if weighted else vy  # (not read without a weight)
        low = floor[(first + r) // cy] if floored else vy  # (max(v, v) is v: one loop for both)
        if rgb.size > 0:  # coloured in the same loop (a second loop over the row, reading it back, cost 10 % more)
            a0, b0, a1, b1, a2, b2 = planes[0, t0], planes[0, t1], planes[1, t0], planes[1, t1], planes[2, t0], \
                planes[2, t1]
            c = rgb[r]
            for x in range(y.size):
                v = max(vy[x], low[x]) if wy[x] < one else vy[x]
                value, ov = _garrote(y[x], v * wy[x] if weighted else v, l0[x], l1[x], v0[x], v1[x], e0[x], e1[x], f)
                o[x] = value
                if with_variance:
                    out_variance[r, x] = ov
                _colour_pixel(value, a0, b0, a1, b1, a2, b2, f, c, x)
            if finite.size > 0:
                finite[r] = _finite_row(c)
            continue
        for x in range(y.size):
            v = max(vy[x], low[x]) if wy[x] < one else vy[x]
            o[x], ov = _garrote(y[x], v * wy[x] if weighted else v, l0[x], l1[x], v0[x], v1[x], e0[x], e1[x], f)
            if with_variance:
                out_variance[r, x] = ov
