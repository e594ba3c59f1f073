"""The log-spline model of the inverse response (step 6 of svelive.calibrate.response): ``log f`` a natural
cubic spline in ``log M`` on knots even in logit(M), fitted by weighted least squares on the log ratio
equations (with a sweep's pixels at white, :mod:`svelive.calibrate.response.censored`, by the probit
likelihood besides), the pilot fit that picks those pixels and the probit's width, and the standard error
of the fitted curve. The spline's evaluation is the Response value type's (svelive.core.response)."""

from __future__ import annotations

import math

import numpy as np

from svelive.calibrate.response.censored import _Censored, _censored_at_white, _frame_pairs, _probit_newton
from svelive.calibrate.response.pairs import _Pairs, _subset
from svelive.core.response import _log_spline_value, log_spline_basis
from svelive.core.sensor import Sensor


def _censored_with_pilot(raws: list[np.ndarray], times: np.ndarray, sensor: Sensor, pairs: _Pairs,
                         exposures: np.ndarray, knots_u: np.ndarray, reach: float = 0.5,
                         margin: float = 0.1) -> _Censored | None:
    """:func:`_censored_at_white` near white, with the probit's width: None when no pair of frames has
    pixels both at and under white there.

    A pilot log-spline on ``knots_u`` fitted to ``pairs`` alone predicts from each darker reading the log
    light in the brighter frame; the rows kept predict it within ``reach`` of white's. The width of a
    pair of frames is the sd of ``log f(brighter) - log f(darker) - log R`` over the pixels predicted
    between ``margin`` and twice that under white (near white, whose noise it is, but where white cannot
    cut the readings off), from the median absolute deviation. It is measured on the pixels themselves:
    a photographed frame's own noise curve counts its texture as noise (Desk, 12 bits: 3 % of full scale
    at M = 0.75, where the photon noise is 0.7 %).
    """
    censored = _censored_at_white(raws, times, sensor)
    pilot = _solve_spline(pairs, exposures, knots_u)[0]
    top, black = int(sensor.white_level), float(sensor.black_level)
    codes = (np.arange(top + 1) - black) / sensor.range_dn
    code_log = np.log(np.maximum(_log_spline_value(pilot, knots_u, codes)[0], 1e-300))
    white = float(np.log(_log_spline_value(pilot, knots_u, np.array([censored.threshold]))[0][0]))
    eta = np.log(np.maximum(_log_spline_value(pilot, knots_u, censored.m)[0], 1e-300)) - white + censored.log_ratio
    keep = np.zeros(censored.m.size, bool)
    width = np.zeros(censored.m.size)
    for q, (j, k) in enumerate(_frame_pairs(times)):
        rows = (censored.pair == q) & (np.abs(eta) < reach)
        if not (censored.clipped[rows].sum() > 0 and (censored.total[rows] - censored.clipped[rows]).sum() > 0):
            continue
        log_ratio = math.log(times[k] / times[j])
        dark, bright = raws[j].ravel(), raws[k].ravel()
        under = (dark > black) & (dark < top) & (bright > black) & (bright < top)
        predicted = code_log[np.clip(dark, 0, top)] - white + log_ratio
        clear = under & (predicted < -margin) & (predicted > -2.0 * margin)
        if np.count_nonzero(clear) < 2:
            continue
        residual = code_log[bright[clear]] - code_log[dark[clear]] - log_ratio
        sd = 1.4826 * float(np.median(np.abs(residual - np.median(residual))))
        if sd > 0:
            keep |= rows
            width[rows] = sd
    if not keep.any():
        return None
    fields = ("m", "log_ratio", "total", "clipped", "pair")
    return _Censored(*(getattr(censored, f)[keep] for f in fields), threshold=censored.threshold, width=width[keep])


def spline_knots(low: float, high: float, count: int) -> np.ndarray:
    """``count`` knots (brightness, float64) uniform in logit(M) = log(M / (1 - M)) from ``low`` to ``high``.

    A film's characteristic curve is close to a logistic function of log exposure, so its
    inverse is close to linear in logit(M): toe and shoulder are both spread out in that
    variable (the inverse S-curve's complex singularities, 0.05 from M = 0 and M = 1, lie
    about pi/2 from the real axis there), and evenly spaced knots in it resolve both ends.
    """
    w = np.linspace(math.log(low / (1.0 - low)), math.log(high / (1.0 - high)), count)
    return 1.0 / (1.0 + np.exp(-w))


def _spline_design(pairs: _Pairs, exposures: np.ndarray, knots_u: np.ndarray):
    """Rows of log f(m_hi) - log f(m_lo) = log R (constant cancelled): (design (P, K-1), target (P,),
    basis slopes at m_lo and m_hi (P, K-1) each)."""
    u_lo, u_hi = np.log(pairs.m_lo), np.log(pairs.m_hi)
    design = log_spline_basis(u_hi, knots_u) - log_spline_basis(u_lo, knots_u)
    target = np.log(exposures[pairs.k_hi] / exposures[pairs.k_lo])
    return (design, target, log_spline_basis(u_lo, knots_u, derivative=True),
            log_spline_basis(u_hi, knots_u, derivative=True))


def _log_sigma(pairs: _Pairs, e_lo: np.ndarray | float, e_hi: np.ndarray | float) -> np.ndarray:
    """Standard deviation of log f(m_hi) - log f(m_lo) from the brightness noise, with elasticities
    d log f / d log M ``e_lo``, ``e_hi``."""
    return np.sqrt((e_hi / pairs.m_hi) ** 2 * pairs.var_hi + (e_lo / pairs.m_lo) ** 2 * pairs.var_lo)


def _solve_spline(pairs: _Pairs, exposures: np.ndarray, knots_u: np.ndarray, sel: np.ndarray | None = None,
                  iterations: int = 3, min_elasticity: float = 0.05, censored: _Censored | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Log-spline coefficients (constant first, log f(1) = 0) minimising the normalised log ratio residuals.

    In ``log f`` a ratio equation is linear with a known right side,
    ``h(m_hi) - h(m_lo) = log R``, so the fit is plain weighted least squares, with no scale to
    fix and no drift where there are no data. Each equation is weighted by its noise
    propagated through ``d log f / dM`` of the previous iteration (a linear camera first);
    the elasticity floor keeps a nearly flat stretch of a bad iterate from taking all the weight.
    With ``censored`` (a sweep's pixels at white, :class:`_Censored`) the likelihood of which pixels
    reach white is maximised together with the least squares (:func:`_probit_newton`).

    Returns (coefficients (K,), weighted design (P, K-1), weighted target (P,)) of the last pass.
    """
    sub = _subset(pairs, slice(None) if sel is None else sel)
    sub = _subset(sub, (sub.m_lo > 0) & (sub.m_hi > 0))
    design, target, d_lo, d_hi = _spline_design(sub, exposures, knots_u)
    e_lo = e_hi = 1.0
    for _ in range(iterations):
        w = 1.0 / _log_sigma(sub, e_lo, e_hi)
        a, b = design * w[:, None], target * w
        rest, *_ = np.linalg.lstsq(a, b, rcond=None)
        if censored is not None:
            rows = (log_spline_basis(np.log(censored.m), knots_u) - log_spline_basis(
                np.array([math.log(censored.threshold)]), knots_u)) / censored.width[:, None]
            offset = censored.log_ratio / censored.width
            rest = _probit_newton(lambda p: rows @ p + offset, rows, rest, censored.total, censored.clipped,
                                  (a.T @ a, a.T @ b, float(b @ b)))
        e_lo = np.maximum(d_lo @ rest, min_elasticity)
        e_hi = np.maximum(d_hi @ rest, min_elasticity)
    constant = -float(log_spline_basis(np.zeros(1), knots_u)[0] @ rest)
    return np.concatenate([[constant], rest]), a, b


def _spline_uncertainty(weighted_design: np.ndarray, scale: float, knots_u: np.ndarray, coef: np.ndarray,
                        grid: np.ndarray) -> np.ndarray:
    """Standard error of f on ``grid`` for a log-spline: that of log f(M) - log f(1) from the least-squares
    covariance (scaled by the reduced chi-square), times f."""
    try:
        cov = np.linalg.inv(weighted_design.T @ weighted_design) * scale
    except np.linalg.LinAlgError:
        return np.full(grid.shape, math.inf)
    f, _ = _log_spline_value(coef, knots_u, grid)
    positive = grid > 0
    g = log_spline_basis(np.log(np.where(positive, grid, 1.0)), knots_u) - log_spline_basis(np.zeros(1), knots_u)
    se = np.sqrt(np.maximum(np.einsum("ij,jk,ik->i", g, cov, g), 0.0))
    return np.where(positive, f * se, 0.0)
