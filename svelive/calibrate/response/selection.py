"""Which model, and where it is trusted (steps 4 and 5 of svelive.calibrate.response): monotonicity on the
measured range, the held-out error over spatial folds of the polynomials and of any model, the jackknife
band from the fits without each fold, and the measured range the data pin down."""

from __future__ import annotations

import math
from typing import Callable

import numpy as np
from numpy.polynomial import polynomial as P

from svelive.calibrate.response.pairs import _Pairs, _subset
from svelive.calibrate.response.polynomial import _design, _residual_sigma, _solve
from svelive.core.response import Response


def _monotone(coef: np.ndarray, measured: tuple[float, float], tolerance: float = 1e-3,
              outside_tolerance: float = 0.01) -> bool:
    """True when the polynomial f is non-decreasing on the measured range (to ``tolerance`` of full
    scale) and nearly so (``outside_tolerance``) where it extrapolates, on the rest of [0, 1]."""
    return _monotone_curve(lambda m: P.polyval(m, coef), measured, tolerance, outside_tolerance)


def _monotone_curve(curve: Callable[[np.ndarray], np.ndarray], measured: tuple[float, float],
                    tolerance: float = 1e-3, outside_tolerance: float = 0.01) -> bool:
    """:func:`_monotone` for any curve f(M)."""
    grid = np.linspace(0.0, 1.0, 1025)
    f = curve(grid)
    drop = np.maximum.accumulate(f) - f
    inside = (grid >= measured[0]) & (grid <= measured[1])
    inside_drop = curve(grid[inside])
    inside_drop = np.maximum.accumulate(inside_drop) - inside_drop
    return bool(inside_drop.max(initial=0.0) <= tolerance and drop.max() <= outside_tolerance)


def _cross_validated(pairs: _Pairs, folds: int, fit: Callable[[np.ndarray], np.ndarray],
                     fold_loss: Callable[[np.ndarray, np.ndarray], np.ndarray],
                     scored: np.ndarray | None = None) -> tuple[float, float, list[np.ndarray]]:
    """Mean and standard error over locations of a held-out loss, and the coefficients fitted without
    each fold (for the jackknife band): ``fit(training selection) -> coefficients``,
    ``fold_loss(coefficients, test selection) -> the loss of the test rows``. ``scored`` (bool (P,),
    None: all): the equations the loss counts (the fits use every training equation); the mean is
    over the locations that have one."""
    loss = np.zeros(pairs.m_lo.size)
    fits = []
    for f in range(folds):
        test = pairs.fold == f
        if not test.any():
            continue
        coef = fit(~test)
        fits.append(coef)
        loss[test] = fold_loss(coef, test)
    location = pairs.location
    if scored is not None:
        loss, location = loss[scored], location[scored]
    _, inverse = np.unique(location, return_inverse=True)
    per_location = np.bincount(inverse, weights=loss)
    return float(per_location.mean()), float(per_location.std(ddof=1) / math.sqrt(per_location.size)), fits


def _held_out(pairs: _Pairs, exposures: np.ndarray, degree: int, folds: int,
              scored: np.ndarray | None = None) -> tuple[float, float, list[np.ndarray]]:
    """:func:`_cross_validated` of the polynomial of ``degree``: the held-out squared normalised residual."""
    A, y = _design(pairs, exposures, degree)

    def fold_loss(coef: np.ndarray, test: np.ndarray) -> np.ndarray:
        sigma = _residual_sigma(_subset(pairs, test), exposures, coef)
        return ((A[test] @ coef[1:] - y[test]) / sigma) ** 2

    return _cross_validated(pairs, folds, lambda train: _solve(pairs, exposures, degree, train), fold_loss, scored)


def _held_out_curve(pairs: _Pairs, exposures: np.ndarray, fit: Callable[[np.ndarray], np.ndarray],
                    curve: Callable[[np.ndarray], Response], folds: int,
                    scored: np.ndarray | None = None) -> tuple[float, float, list[np.ndarray]]:
    """:func:`_held_out` for any model: ``fit(training selection) -> coefficients``,
    ``curve(coefficients) -> Response``; the held-out loss is the polynomial's, the ratio residual
    ``f(m_hi) / R - f(m_lo)`` over its noise through the model's own slope, so the two compare."""
    inv_r = exposures[pairs.k_lo] / exposures[pairs.k_hi]

    def fold_loss(coef: np.ndarray, test: np.ndarray) -> np.ndarray:
        response = curve(coef)
        sub = _subset(pairs, test)
        sigma = _slope_sigma(sub, inv_r[test], response.slope(sub.m_lo), response.slope(sub.m_hi))
        return ((response(sub.m_hi) * inv_r[test] - response(sub.m_lo)) / sigma) ** 2

    return _cross_validated(pairs, folds, fit, fold_loss, scored)


def _slope_sigma(pairs: _Pairs, inv_r: np.ndarray, slope_lo: np.ndarray, slope_hi: np.ndarray,
                 min_slope: float = 0.01) -> np.ndarray:
    """:func:`_residual_sigma` from given slopes of f at m_lo and m_hi."""
    d_lo, d_hi = np.maximum(slope_lo, min_slope), np.maximum(slope_hi, min_slope)
    return np.sqrt((d_hi * inv_r) ** 2 * pairs.var_hi + d_lo**2 * pairs.var_lo)


def _jackknife_error(fold_fits: list[Response], grid: np.ndarray) -> np.ndarray:
    """Delete-a-group jackknife standard error of f on ``grid`` from the fits without each spatial fold.

    Unlike the covariance it sees that neighbouring equations share pixels and scene
    content (each fold is a set of image blocks), so it is the honest spread of the fit
    over scenes like this one; neither sees a model that is too stiff.
    """
    n = len(fold_fits)
    if n < 2:
        return np.full(grid.shape, math.inf)
    curves = np.stack([curve(grid) for curve in fold_fits])
    return np.sqrt((n - 1) / n * np.sum((curves - curves.mean(axis=0)) ** 2, axis=0))


def _pinned_range(pairs: _Pairs, uncertainty: np.ndarray, grid: np.ndarray, max_uncertainty: float,
                  bins: int, min_count: int) -> tuple[float, float]:
    """Longest brightness interval on which the curve is pinned down by data: every one of
    ``bins`` equal bins in it holds at least ``min_count`` equation ends, and the standard
    error stays within ``max_uncertainty``. (0, 0) when there is none."""
    ends = np.concatenate([pairs.m_lo, pairs.m_hi])
    count = np.bincount(np.clip((ends * bins).astype(np.int64), 0, bins - 1), minlength=bins)
    worst = np.zeros(bins)
    np.maximum.at(worst, np.clip((grid * bins).astype(np.int64), 0, bins - 1), uncertainty)
    good = (count >= min_count) & (worst <= max_uncertainty)
    best, start = (0, 0), None
    for i, g in enumerate(np.append(good, False)):
        if g and start is None:
            start = i
        elif not g and start is not None:
            if i - start > best[1] - best[0]:
                best = (start, i)
            start = None
    if best == (0, 0):
        return 0.0, 0.0
    lo = max(best[0] / bins, float(ends.min()))
    hi = min(best[1] / bins, float(ends.max()))
    return lo, hi


def _model_name(kind: str, size: int) -> str:
    """Key of a candidate model in ``stats.held_out_error``: the degree ("3") or "log-spline 6" (knots)."""
    return str(size) if kind == "polynomial" else f"log-spline {size}"
