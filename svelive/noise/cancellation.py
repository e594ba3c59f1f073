"""The noise line of one frame with texture cancelled across exposures (:func:`cancellation_fit`).

Texture that passes the residual estimator's tests (svelive/noise/frame.py) still grows with the signal
like shot noise, so a textured frame reads the gain low. Residuals of one geometry (colour, offset,
exposure ratio) at two or more base exposures ``e`` see the same texture scaled by ``e^2`` and
shot noise by ``e``. Taken in the same cells (all of a cell's residuals kept or dropped together,
binned and tested by the other cells of its block, never by their own readings), their bin means
are ``t / gain + R + c D`` with one unknown texture ``D`` per geometry and bin, fitted jointly
(:func:`joint_texture_fit`). The fit's bins are correlated (shared readings, shared texture, texture
that differs between exposures over the frame): its variance is at least that of a delete-one-band
jackknife (:func:`_with_jackknife`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from svelive.noise.inputs import _block_lines, _fixed, _high_level, _layout
from svelive.noise.model import QUANTISATION_VARIANCE, EstimatorConfig, LineFit
from svelive.noise.stats import chi2_quantile_array

if TYPE_CHECKING:  # the Camera is only read here (its pattern, colour filter and sensor)
    from svelive.core.camera import Camera


@dataclass(frozen=True)
class _Residual:
    """A residual ``x_p - mean_k(e_p / e_q x_q)`` of the pixel at tile phase (a, b) and its neighbours at
    ``offsets`` (dy, dx) from it, all of one exposure ``e_q >= e_p`` and of the pixel's colour."""

    a: int
    b: int
    offsets: tuple[tuple[int, int], ...]


def _cancellation_geometries(tile_e: np.ndarray, tile_c: np.ndarray | None,
                             reach: int) -> list[list[_Residual]]:
    """Residuals of the same geometry at two or more base exposures, grouped by geometry.

    A geometry is a colour, an offset ``k`` (symmetric ``(k, -k)`` where both sides have the same
    exposure, which cancels a linear gradient; else one side) and an exposure ratio ``e_q / e_p >= 1``.
    Its residuals see the scene's texture at that offset scaled by ``e_p``, so with two base exposures
    texture (``e_p^2``) and shot noise (``e_p``) can be told apart. Only the nearest ring that gives
    any geometry is used (nearer neighbours, less texture). [] when the pattern has none (one exposure
    per colour, or no two base exposures sharing a geometry).
    """
    ph, pw = tile_e.shape

    def exposure(y: int, x: int) -> float:
        return float(tile_e[y % ph, x % pw])

    def colour(y: int, x: int) -> int | None:
        return None if tile_c is None else int(tile_c[y % ph, x % pw])

    for r in range(1, reach + 1):
        ring = [(dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1)
                if max(abs(dy), abs(dx)) == r and (dy, dx) > (-dy, -dx)]
        found: dict[tuple, list[tuple[_Residual, float]]] = {}
        for a in range(ph):
            for b in range(pw):
                e_p, c_p = exposure(a, b), colour(a, b)
                for k in ring:
                    plus, minus = (a + k[0], b + k[1]), (a - k[0], b - k[1])
                    ok_plus = colour(*plus) == c_p and exposure(*plus) >= e_p
                    ok_minus = colour(*minus) == c_p and exposure(*minus) >= e_p
                    if ok_plus and ok_minus and exposure(*plus) == exposure(*minus):
                        key = (c_p, k, 2, exposure(*plus) / e_p)
                        found.setdefault(key, []).append((_Residual(a, b, (k, (-k[0], -k[1]))), e_p))
                        continue
                    for sign, ok, q in ((1, ok_plus, plus), (-1, ok_minus, minus)):
                        # a pair of equal exposures is the same pair seen from either end: once
                        if ok and not (sign < 0 and exposure(*q) == e_p):
                            key = (c_p, k, 1, exposure(*q) / e_p)
                            found.setdefault(key, []).append((_Residual(a, b, ((sign * k[0], sign * k[1]),)), e_p))
        groups = [[res for res, _ in items] for items in found.values() if len({e for _, e in items}) >= 2]
        if groups:
            return groups
    return []


def _disjoint_cells(reads: set[tuple[int, int]], ph: int, pw: int) -> tuple[int, int]:
    """The smallest cell (rows, columns; multiples of the tile) such that the readings of a cell and of
    any cell up to two cells away are disjoint: a cell's binning and flatness statistics come from the
    other cells of its block, and must not see its own readings."""
    best = (8 * ph, 8 * pw)
    for my in range(1, 8):
        for mx in range(1, 8):
            cy, cx = my * ph, mx * pw
            if cy * cx >= best[0] * best[1]:
                continue
            shifts = [(i * cy, j * cx) for i in range(-2, 3) for j in range(-2, 3) if (i, j) != (0, 0)]
            if all((d[0] + sy, d[1] + sx) not in reads for d in reads for sy, sx in shifts):
                best = (cy, cx)
    return best


@dataclass(frozen=True)
class _CellData:
    """One geometry's readings in blocks of 3x3 cells, gathered once and re-selected at every iteration.

    Attributes:
        x: float64 (K, N), the K readings of every cell (signal above black, DN).
        e: float64 (K, 1), their exposures.
        u: float64 (J, N), each residual's square, normalised so that ``E[u] = t / gain + R + c D``
            (``D`` the texture of the geometry at that level), DN^2.
        t: float64 (J, N), the shot coordinate from the cell's own readings (unbiased), DN.
        c: float64 (J,), the texture coefficient ``e_p^2 / sum coef^2``.
        block: int64 (N,), the block of every cell; blocks: number of blocks; others: float64 (N,),
            the other cells of the block.
        symmetric: every residual of the geometry has neighbours on both sides (cancels a gradient).
    """

    x: np.ndarray
    e: np.ndarray
    u: np.ndarray
    t: np.ndarray
    c: np.ndarray
    block: np.ndarray
    blocks: int
    others: np.ndarray
    symmetric: bool


def _cancellation_gather(source: np.ndarray, offset: float, tile_e: np.ndarray, groups: list[list[_Residual]],
                         high: float, config: EstimatorConfig) -> list[_CellData]:
    """Every geometry's readings in blocks of 3x3 cells (a strided subset of the frame, about
    ``config.cancel_max_samples`` residuals in all). A cell with a reading at or above ``high`` is dropped."""
    ph, pw = tile_e.shape
    h, w = source.shape
    side = config.block
    total = sum(len(g) for g in groups)
    out = []
    for group in groups:
        reads = sorted({(r.a + d[0], r.b + d[1]) for r in group for d in ((0, 0), *r.offsets)})
        cy, cx = _disjoint_cells(set(reads), ph, pw)
        lo_y, hi_y = max(0, -min(d[0] for d in reads)), max(0, max(d[0] for d in reads))
        lo_x, hi_x = max(0, -min(d[1] for d in reads)), max(0, max(d[1] for d in reads))
        first_y, first_x = lo_y + (-lo_y) % ph, lo_x + (-lo_x) % pw
        cells = max((h - first_y - hi_y) // cy, 0) * max((w - first_x - hi_x) // cx, 0)
        stride = max(side, int(math.ceil(side * math.sqrt(cells * total / config.cancel_max_samples))))
        rows = _block_lines(first_y, h - hi_y - cy + 1, cy, stride, side)
        cols = _block_lines(first_x, w - hi_x - cx + 1, cx, stride, side)
        if rows.size == 0 or cols.size == 0:
            continue
        by, bx = rows.size // side, cols.size // side
        block = np.broadcast_to(np.arange(by)[:, None, None, None] * bx + np.arange(bx)[None, None, :, None],
                                (by, side, bx, side)).ravel()
        x = np.stack([source[np.ix_(rows + dy, cols + dx)].astype(np.float64).ravel() for dy, dx in reads])
        x -= offset
        ok = np.all(x < high, axis=0)
        index = {d: k for k, d in enumerate(reads)}
        e = np.array([[float(tile_e[dy % ph, dx % pw])] for dy, dx in reads])
        coef = np.zeros((len(group), len(reads)))
        for j, res in enumerate(group):
            e_p = float(tile_e[res.a % ph, res.b % pw])
            coef[j, index[(res.a, res.b)]] = 1.0
            for dy, dx in res.offsets:
                q = index[(res.a + dy, res.b + dx)]
                coef[j, q] -= e_p / e[q, 0] / len(res.offsets)
        x, block = np.ascontiguousarray(x[:, ok]), block[ok]
        # a residual r = coef . x has variance sum coef^2 (e L / g + R) + texture; normalised by sum coef^2
        size = (coef * coef).sum(axis=1)
        r = coef @ x
        e_p = (coef > 0) @ e[:, 0]
        others = np.bincount(block, None, by * bx)[block] - 1.0
        out.append(_CellData(x, e, r * r / size[:, None], ((coef * coef) @ x) / size[:, None], e_p * e_p / size,
                             block, by * bx, others, all(len(r.offsets) == 2 for r in group)))
    return out


@dataclass(frozen=True)
class _CancellationSamples:
    """One geometry's selected cells.

    Attributes:
        coord: float64 (N,), the binning coordinate, ``log(L e_max + 2)`` of the level ``L`` of the
            other cells of the block (never of the cell's own readings).
        u: float64 (J, N), squared residuals normalised so that ``E[u] = t / gain + R + c D``, DN^2.
        t: float64 (J, N), the shot coordinate from the cell's own readings (unbiased), DN.
        c: float64 (J,), the texture coefficient ``e_p^2 / sum coef^2``.
        region: int64 (N,), the horizontal band of the frame the cell's block lies in, in
            ``[0, config.cancel_jackknife)`` (the units :func:`_with_jackknife` leaves out).
        symmetric: the geometry's residuals have neighbours on both sides (:func:`_without_gradient_bias`).
    """

    coord: np.ndarray
    u: np.ndarray
    t: np.ndarray
    c: np.ndarray
    region: np.ndarray
    symmetric: bool


def _cancellation_select(data: _CellData, model: tuple[float, float], floor: float, high: float,
                         config: EstimatorConfig) -> _CancellationSamples | None:
    """The cells of one geometry at flat, unclipped places under the model ``(slope, intercept)``; all of a
    cell's residuals are kept or dropped together, so every exposure sees the same texture.

    - The level ``L`` of a cell is its readings' generalised-least-squares mean (weights
      ``e / var``): for Gaussian noise it is independent of every residual, whose mean is 0 on a flat
      scene. The level of the other cells of its block bins it and tests its clipping.
    - Flat at the cell scale: the lowest exposure sees the cell's level and its block's differ by
      at most its noise (``config.cancel_level`` times its variance).
    - Flat around it: within every bin the ``config.cancel_fraction`` of cells whose block's other
      cells have the smallest standardised residuals are kept, and (``config.cancel_flat``) every cell
      whose block's other cells are as flat as noise: their standardised residuals, chi-square with
      (residuals x cells) degrees of freedom where the block is flat, below its ``config.region_quantile``.
      Where texture is small against the noise (dark or flat places) a fixed fraction would throw
      usable cells away; where it dominates, the fraction still applies.
    None when fewer than ``config.min_bin`` cells remain.
    """
    slope, intercept = model
    x, e = data.x, data.e
    if x.shape[1] < config.min_bin:
        return None
    level = x.sum(axis=0) / e.sum()
    weights = e / np.maximum(slope * e * np.maximum(level, 0.0) + intercept, QUANTISATION_VARIANCE)
    level = (weights * x).sum(axis=0) / (weights * e).sum(axis=0)
    count = data.others
    around = (np.bincount(data.block, level, data.blocks)[data.block] - level) / np.maximum(count, 1.0)
    keep = count >= 4
    # clipping, tested at every distinct exposure from the block's level and from the cell's own
    for e_k in np.unique(e[:, 0]):
        for lv in (around, level):
            sd = np.sqrt(np.maximum(slope * e_k * np.maximum(lv, 0.0) + intercept, QUANTISATION_VARIANCE))
            keep &= (e_k * lv - 4.0 * sd >= floor) & (e_k * lv + 4.0 * sd < high)
    e_low = float(e.min())
    var_low = np.maximum(slope * e_low * np.maximum(around, 0.0) + intercept, QUANTISATION_VARIANCE)
    keep &= (e_low * (level - around)) ** 2 <= config.cancel_level * var_low
    if np.count_nonzero(keep) < config.min_bin:
        return None
    u, t = data.u, data.t
    z = (u / np.maximum(slope * np.maximum(t, 0.0) + intercept, QUANTISATION_VARIANCE)).sum(axis=0)
    region = (np.bincount(data.block, z, data.blocks)[data.block] - z) / np.maximum(count, 1.0)
    coord = np.log(np.maximum(around, 0.0) * float(e.max()) + 2.0)
    which = _bins_of(coord, keep, config.cancel_bins)
    # within every bin, the cells at or below its cancel_fraction quantile of the region statistic
    limit = np.full(config.cancel_bins, -np.inf)
    for k in range(config.cancel_bins):
        inside = region[keep & (which == k)]
        if inside.size:
            limit[k] = np.quantile(inside, config.cancel_fraction)
    flattest = region <= limit[which]
    if config.cancel_flat:
        # and wherever the block is as flat as noise: the others' summed z is chi-square with J per cell
        cells = np.maximum(count, 1.0)
        flattest |= region <= chi2_quantile_array(config.region_quantile, u.shape[0] * cells) / cells
    keep &= flattest
    if np.count_nonzero(keep) < config.min_bin:
        return None
    region = data.block[keep] * max(config.cancel_jackknife, 1) // data.blocks
    return _CancellationSamples(coord[keep], u[:, keep], t[:, keep], data.c, region, data.symmetric)


def _bins_of(coord: np.ndarray, where: np.ndarray, bins: int) -> np.ndarray:
    """Equal-width bins of ``coord`` over its range at ``where``: int64 (N,) in [0, bins)."""
    lo, hi = float(coord[where].min()), float(coord[where].max())
    return np.clip(((coord - lo) / max(hi - lo, 1e-9) * bins).astype(np.int64), 0, bins - 1)


def _cancellation_table(parts: list[_CancellationSamples], config: EstimatorConfig) -> tuple[np.ndarray, ...]:
    """Per geometry, bin and residual: (group id, mean t, c, mean u, count), float64/.../int64 (M,) each;
    a group is one geometry's bin (its texture is one unknown). Bins with fewer than ``config.min_bin``
    cells are left out."""
    gid, t, c, u, n = [], [], [], [], []
    group = 0
    for part in parts:
        which = _bins_of(part.coord, np.ones(part.coord.shape, bool), config.cancel_bins)
        counts = np.bincount(which, minlength=config.cancel_bins)
        sum_t = np.stack([np.bincount(which, tj, config.cancel_bins) for tj in part.t])
        sum_u = np.stack([np.bincount(which, uj, config.cancel_bins) for uj in part.u])
        for k in np.flatnonzero(counts >= config.min_bin):
            for j in range(part.u.shape[0]):
                gid.append(group)
                t.append(sum_t[j, k] / counts[k])
                c.append(part.c[j])
                u.append(sum_u[j, k] / counts[k])
                n.append(counts[k])
            group += 1
    return (np.array(gid, np.int64), np.array(t), np.array(c), np.array(u), np.array(n, np.int64))


def joint_texture_fit(gid: np.ndarray, t: np.ndarray, c: np.ndarray, u: np.ndarray, n: np.ndarray, *,
                      slope: float | None = None, intercept: float | None = None,
                      mismatch: float = 0.1) -> LineFit | None:
    """Weighted least squares of ``u = slope t + intercept + c D_g`` with one texture ``D_g`` per group.

    A group holds the bins of one geometry and signal level at two or more base exposures: texture
    scales as ``c`` (the exposure squared), shot noise as ``t`` (the exposure), so the two are told
    apart and the texture ``D_g`` (of any sign: a bound would keep only the groups whose texture
    happened to fluctuate up, and bias the slope) is fitted away. A bin mean's variance is
    ``2 m^2 / n`` (``m`` the fitted value) plus ``(mismatch * c D_g)^2``: the texture two exposures
    see is equal only to within ``mismatch`` (they sample neighbouring rows or columns), so bins where
    texture dominates weigh little. The covariance is scaled up by the reduced chi-square. A given
    ``slope`` or ``intercept`` is held fixed. None when the system is underdetermined or the slope
    not positive. The texture unknowns are profiled out group by group (no matrix with a column per
    group), which gives the same line and covariance as the full least squares.
    """
    groups = int(gid.max()) + 1 if gid.size else 0
    free = [slope is None, intercept is None]
    cols = np.array([a for a, f in zip((t, np.ones_like(t)), free) if f])
    if u.size < groups + len(cols) + 2 or not len(cols):
        return None
    target = u - (slope or 0.0) * t - (intercept or 0.0)
    fitted = np.maximum(u, QUANTISATION_VARIANCE)
    tex = np.zeros_like(u)
    for _ in range(6):
        w2 = 1.0 / (2.0 * fitted * fitted / n + (mismatch * tex) ** 2)
        # the texture unknowns profiled out (Frisch-Waugh-Lovell): within each group the part of the
        # line's columns and of the target that c explains is removed, and the line's own weighted least
        # squares on what is left gives the joint solution's slope, intercept and covariance exactly
        # (a 2x2 system instead of one with a column per group)
        cc = np.bincount(gid, w2 * c * c, groups)[gid]
        x_res = cols - c * np.stack([np.bincount(gid, w2 * c * col, groups)[gid] for col in cols]) / cc
        y_res = target - c * np.bincount(gid, w2 * c * target, groups)[gid] / cc
        normal = (x_res * w2) @ x_res.T
        sol = np.linalg.pinv(normal) @ ((x_res * w2) @ y_res)
        resid = y_res - sol @ x_res
        tex = np.abs(target - sol @ cols - resid)  # |c D_g|
        fitted = np.maximum(u - resid, QUANTISATION_VARIANCE)
    dof = max(u.size - groups - len(cols), 1)
    chi2 = float((resid * resid * w2).sum()) / dof
    sub = np.linalg.pinv(normal) * max(chi2, 1.0)
    coef = [slope or 0.0, intercept or 0.0]
    cov = np.zeros((2, 2))
    idx = [k for k, f in enumerate(free) if f]
    for i, ki in enumerate(idx):
        coef[ki] = float(sol[i])
        for j, kj in enumerate(idx):
            cov[ki, kj] = sub[i, j]
    if not coef[0] > 0 or not np.all(np.isfinite(cov)):
        return None
    return LineFit(coef[0], coef[1], cov, t, u, n, np.ones(u.size, bool), not free[0])


def cancellation_fit(source: np.ndarray, offset: float, floor: float, camera: Camera,
                     config: EstimatorConfig = EstimatorConfig(), start: LineFit | None = None) -> LineFit | None:
    """The noise line of one frame with texture cancelled across exposures (see the module docstring and
    docs/noise.md), or None where the pattern, the frame or the fit cannot give it (no geometry at two
    base exposures, a calibrated per-pixel exposure map, too few flat cells, an ill-posed fit).

    ``source - offset`` is the signal above black; ``floor`` the lowest signal a reading can take (DN).
    ``start``: a line the selection's first pass may use (the residual fit of the same frame), which
    saves the pass under the sensor defaults.
    """
    tile_e, tile_c, pixel_map = _layout(camera)
    groups = _cancellation_geometries(tile_e, tile_c, config.reach)
    if not groups or pixel_map is not None:
        return None
    sensor = camera.sensor
    high = _high_level(sensor)
    data = _cancellation_gather(source, offset, tile_e, groups, high, config)
    fixed = _fixed(sensor)
    model = (fixed["slope"] or 1.0 / sensor.effective_gain,
             fixed["intercept"] if fixed["intercept"] is not None else sensor.floor_variance)
    passes = 1 + config.cancel_iterations
    if start is not None:
        model, passes = (start.slope, max(start.intercept, QUANTISATION_VARIANCE)), config.cancel_iterations
    fit = None
    for _ in range(max(passes, 1)):
        parts = [p for d in data if (p := _cancellation_select(d, model, floor, high, config)) is not None]
        if not parts:
            return None
        fit = joint_texture_fit(*_cancellation_table(parts, config), **fixed, mismatch=config.cancel_mismatch)
        if fit is None:
            return None
        model = (fit.slope, max(fit.intercept, QUANTISATION_VARIANCE))
    if fit is not None and config.cancel_jackknife > 1:
        fit = _with_jackknife(fit, parts, fixed, config)
    if fit is not None and config.cancel_symmetric:
        fit = _without_gradient_bias(fit, parts, fixed, config)
    return fit


def _without_gradient_bias(fit: LineFit, parts: list[_CancellationSamples], fixed: dict,
                           config: EstimatorConfig) -> LineFit:
    """``fit``, or the joint fit of its symmetric geometries alone where the one-sided ones bias it.

    A one-sided residual keeps the scene's gradient, which base exposures a row or more apart see
    differently (``1/1/8/8``: three one-sided geometries across rows beside the pairs along the row):
    a bias that more data does not shrink, while their residuals make the fit more precise (small
    frames need them). The same selected cells are fitted without them; where the two slopes agree
    within two of the symmetric fit's standard deviations and ``fit`` states the smaller uncertainty,
    ``fit`` is kept, else the symmetric fit (as :func:`_preferred` weighs the residual fit against the
    joint one)."""
    symmetric = [p for p in parts if p.symmetric]
    if not symmetric or len(symmetric) == len(parts):
        return fit
    sym = joint_texture_fit(*_cancellation_table(symmetric, config), **fixed, mismatch=config.cancel_mismatch)
    if sym is None:
        return fit
    if config.cancel_jackknife > 1:
        sym = _with_jackknife(sym, symmetric, fixed, config)
    return fit if _no_bias_shown(fit, sym) else sym


def _no_bias_shown(precise: LineFit, unbiased: LineFit) -> bool:
    """True where the slope of ``precise`` (a fit open to a bias) lies within two of the ``unbiased`` fit's
    standard deviations of its slope and ``precise`` states the smaller uncertainty: then the data show no
    bias and the more precise fit is the better one."""
    return (precise.slope - unbiased.slope) ** 2 <= 4.0 * unbiased.cov[0, 0] and precise.cov[0, 0] <= unbiased.cov[0, 0]


def _with_jackknife(fit: LineFit, parts: list[_CancellationSamples], fixed: dict,
                    config: EstimatorConfig) -> LineFit:
    """``fit`` with its covariance raised to the delete-one-band jackknife's where that is larger.

    The fit's own covariance treats every bin mean as independent with the variance of ``n``
    independent squared residuals. They are not: a cell's residuals share readings, neighbouring
    cells share texture, and what the two exposures of a geometry see differs by a texture that
    varies over the frame. Leaving out one horizontal band of blocks at a time
    (``config.cancel_jackknife`` bands, all geometries together, the bins kept) and refitting the
    same selected cells measures the spread all of these give, whatever their correlation, without
    a model of it. The line itself is left as fitted."""
    bands = config.cancel_jackknife
    sums = []  # per geometry: counts (bands, bins), sums of t and u (J, bands, bins), c (J,)
    for part in parts:
        which = _bins_of(part.coord, np.ones(part.coord.shape, bool), config.cancel_bins)
        index = part.region * config.cancel_bins + which
        size = bands * config.cancel_bins
        counts = np.bincount(index, minlength=size).reshape(bands, config.cancel_bins)
        sum_t = np.stack([np.bincount(index, tj, size) for tj in part.t]).reshape(-1, bands, config.cancel_bins)
        sum_u = np.stack([np.bincount(index, uj, size) for uj in part.u]).reshape(-1, bands, config.cancel_bins)
        sums.append((counts, sum_t, sum_u, part.c))
    estimates = []
    for g in range(bands):
        gid, t, c, u, n = [], [], [], [], []
        group = 0
        for counts, sum_t, sum_u, coef in sums:
            cnt = counts.sum(axis=0) - counts[g]
            st = sum_t.sum(axis=1) - sum_t[:, g]
            su = sum_u.sum(axis=1) - sum_u[:, g]
            for k in np.flatnonzero(cnt >= config.min_bin):
                gid += [group] * coef.size
                t += list(st[:, k] / cnt[k])
                c += list(coef)
                u += list(su[:, k] / cnt[k])
                n += [cnt[k]] * coef.size
                group += 1
        other = joint_texture_fit(np.array(gid, np.int64), np.array(t), np.array(c), np.array(u),
                                  np.array(n, np.int64), **fixed, mismatch=config.cancel_mismatch)
        if other is None:
            return fit  # a band the fit cannot do without: the jackknife is undefined
        estimates.append((other.slope, other.intercept))
    est = np.array(estimates)
    dev = est - est.mean(axis=0)
    jack = (bands - 1) / bands * (dev.T @ dev)
    extra = np.maximum(np.diag(jack) - np.diag(fit.cov), 0.0)
    return replace(fit, cov=fit.cov + np.diag(extra))
