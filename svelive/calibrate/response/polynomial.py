"""The polynomial model of the inverse response (step 3 of svelive.calibrate.response): its ratio equations
with f(1) = 1 eliminated, their noise through f', the scale-free solve in a Legendre basis, and the
standard error of the fitted curve from the least-squares covariance."""

from __future__ import annotations

import math

import numpy as np
from numpy.polynomial import legendre as L
from numpy.polynomial import polynomial as P

from svelive.calibrate.response.pairs import _Pairs, _subset


def _design(pairs: _Pairs, exposures: np.ndarray, degree: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows of f(m_hi) / R - f(m_lo) = 0 with c_0 eliminated by f(1) = 1: A c_{1..N} = y."""
    inv_r = exposures[pairs.k_lo] / exposures[pairs.k_hi]
    n = np.arange(1, degree + 1)
    A = (pairs.m_hi[:, None] ** n - 1.0) * inv_r[:, None] - (pairs.m_lo[:, None] ** n - 1.0)
    y = inv_r - 1.0
    return A, -y


def _residual_sigma(pairs: _Pairs, exposures: np.ndarray, coef: np.ndarray | None,
                    min_slope: float = 0.01) -> np.ndarray:
    """Standard deviation of each equation's residual; slopes from ``coef`` (None: a linear f).

    Propagating the brightness noise through f' makes the normalised residual
    independent of the scale of f, so a curve cannot lower it by flattening
    where the data are; the floor keeps a flat stretch from taking all the weight.
    """
    inv_r = exposures[pairs.k_lo] / exposures[pairs.k_hi]
    if coef is None:
        d_lo = d_hi = 1.0
    else:
        der = P.polyder(coef)
        d_lo = np.maximum(P.polyval(pairs.m_lo, der), min_slope)
        d_hi = np.maximum(P.polyval(pairs.m_hi, der), min_slope)
    return np.sqrt((d_hi * inv_r) ** 2 * pairs.var_hi + d_lo**2 * pairs.var_lo)


def _solve(pairs: _Pairs, exposures: np.ndarray, degree: int, sel: np.ndarray | None = None,
           iterations: int = 3) -> np.ndarray:
    """Power-series coefficients (c_0 first, f(1) = 1) minimising the normalised ratio residuals.

    The residuals ``f(m_hi) / R - f(m_lo)`` are linear in f, but with f(1) = 1 imposed
    where there are no data, least squares drifts towards a curve that is nearly
    flat (small) where the data are. Instead the shape is found scale-free: the
    Rayleigh quotient ``sum (r_i / s_i)^2 / sum ((f(m_lo)^2 + (f(m_hi)/R)^2) / s_i^2)``
    is minimised (smallest generalised eigenvector, Legendre basis on [0, 1] for
    conditioning), then scaled to f(1) = 1. The standard deviations ``s_i`` come from
    the previous iteration's slope (a straight line first) and stay fixed within one
    solve, so the problem is a plain quadratic one.
    """
    sub = _subset(pairs, slice(None) if sel is None else sel)
    inv_r = exposures[sub.k_lo] / exposures[sub.k_hi]
    v_lo = L.legvander(2.0 * sub.m_lo - 1.0, degree)
    v_hi = L.legvander(2.0 * sub.m_hi - 1.0, degree) * inv_r[:, None]
    coef = None
    for _ in range(iterations):
        w = 1.0 / _residual_sigma(sub, exposures, coef)
        a = (v_hi - v_lo) * w[:, None]
        b_lo, b_hi = v_lo * w[:, None], v_hi * w[:, None]
        num = a.T @ a
        den = b_lo.T @ b_lo + b_hi.T @ b_hi
        den += 1e-12 * np.trace(den) * np.eye(degree + 1)
        chol_inv = np.linalg.inv(np.linalg.cholesky(den))
        _, vectors = np.linalg.eigh(chol_inv @ num @ chol_inv.T)
        leg = chol_inv.T @ vectors[:, 0]
        leg /= L.legval(1.0, leg)
        coef = L.Legendre(leg, domain=[0.0, 1.0]).convert(kind=P.Polynomial).coef
        coef = np.pad(coef, (0, degree + 1 - coef.size))
    return coef


def _curve_uncertainty(weighted_design: np.ndarray, scale: float, grid: np.ndarray) -> np.ndarray:
    """Standard error of f at every brightness of ``grid`` (fraction of full scale), from the
    least-squares covariance of the coefficients (f(1) = 1 eliminated) scaled by the reduced
    chi-square. Only noise: it does not see a wrong model, hence also the coverage test."""
    normal = weighted_design.T @ weighted_design
    try:
        cov = np.linalg.inv(normal) * scale
    except np.linalg.LinAlgError:
        return np.full(grid.shape, math.inf)
    n = np.arange(1, weighted_design.shape[1] + 1)
    basis = grid[:, None] ** n - 1.0
    return np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", basis, cov, basis), 0.0))
