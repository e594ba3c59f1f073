"""Robust statistics of noise samples and the weighted line fit: signal bins, their robust variances, the line
``variance = t / gain + R`` through them, and chi-square quantiles for the flatness tests.

The uncertainty is the weighted fit's covariance (bins weighted by the variance of a variance estimate,
``2 v^2 / n``), scaled up by the reduced chi-square when the bins scatter more than that.
"""

from __future__ import annotations

import math
from dataclasses import replace
from functools import lru_cache
from statistics import NormalDist

import numpy as np

from svelive.core.order import median, quantile
from svelive.noise.model import QUANTISATION_VARIANCE, EstimatorConfig, LineFit, NoiseSamples


def chi2_quantile(q: float, dof: int) -> float:
    """Quantile ``q`` of chi-square with ``dof`` (>= 1) degrees of freedom, a float: the Wilson-Hilferty
    approximation, held at 0 where it would fall below (tiny ``q`` at one or two degrees of freedom)."""
    z = _normal_quantile(q)
    t = 2.0 / (9.0 * dof)
    return dof * max(1.0 - t + z * math.sqrt(t), 0.0) ** 3


def _normal_quantile(q: float) -> float:
    """The standard normal distribution's quantile ``q``."""
    return NormalDist().inv_cdf(q)


def chi2_quantile_array(q: float, dof: np.ndarray) -> np.ndarray:
    """:func:`chi2_quantile` for an array of degrees of freedom (>= 1), float64."""
    z = _normal_quantile(q)
    d = np.maximum(dof, 1).astype(np.float64)
    t = 2.0 / (9.0 * d)
    return d * np.maximum(1.0 - t + z * np.sqrt(t), 0.0) ** 3


def _normal_cdf(x: np.ndarray) -> np.ndarray:
    """Standard normal CDF, float64, |error| < 2e-7 (Abramowitz and Stegun 7.1.26 for erf)."""
    z = np.abs(x) / math.sqrt(2.0)
    k = 1.0 / (1.0 + 0.3275911 * z)
    poly = k * (0.254829592 + k * (-0.284496736 + k * (1.421413741 + k * (-1.453152027 + k * 1.061405429))))
    erf = 1.0 - poly * np.exp(-z * z)
    return 0.5 * (1.0 + np.sign(x) * erf)


@lru_cache(maxsize=1)
def _median_table() -> tuple[np.ndarray, np.ndarray]:
    """(sigma^2 + 1/12, median of (g + q)^2) for g ~ N(0, sigma^2) and q ~ U(-1/2, 1/2), over a sigma grid:
    the median of a rounded reading's squared residual, which for small sigma is not 0.455 of the variance.
    Read-only arrays, computed once."""
    sigmas = np.geomspace(0.05, 100.0, 100)[:, None]
    u = ((np.arange(32) + 0.5) / 32 - 0.5)[None, :]  # quadrature over the rounding error
    lo, hi = np.zeros_like(sigmas), 0.5 + 8 * sigmas
    for _ in range(36):  # bisection on P(|g + q| <= x) = 1/2
        x = 0.5 * (lo + hi)
        p = np.mean(_normal_cdf((x - u) / sigmas) - _normal_cdf((-x - u) / sigmas), axis=1, keepdims=True)
        lo, hi = np.where(p < 0.5, x, lo), np.where(p < 0.5, hi, x)
    variance, medians = sigmas[:, 0] ** 2 + QUANTISATION_VARIANCE, (0.5 * (lo + hi))[:, 0] ** 2
    variance.setflags(write=False)
    medians.setflags(write=False)
    return variance, medians


def _variance_from_median(median: float, table: tuple[np.ndarray, np.ndarray]) -> float:
    """The variance (DN^2, quantisation included) whose rounded-Gaussian residual has this median square."""
    variance, medians = table
    if median >= medians[-1]:
        return median / 0.45493642  # Gaussian: the median of chi-square with one degree of freedom
    return float(np.interp(median, medians, variance))


def _clip_correction(k: float) -> float:
    """E[z^2 | |z| < k] for a standard normal z: the factor a k-sigma clipped mean square falls short by."""
    phi = math.exp(-0.5 * k * k) / math.sqrt(2 * math.pi)
    return 1.0 - 2.0 * k * phi / math.erf(k / math.sqrt(2))


def _median_and_quantile(u: np.ndarray, q: float) -> tuple[float, float]:
    """``np.median(u)`` and ``np.quantile(u, q)`` (linear interpolation, numpy's formula) of ``u`` (float64 (N,),
    N >= 1), by one partition each (svelive.core.order)."""
    return float(median(u)), quantile(u, q)


def _robust_variance(u: np.ndarray, clip_sigma: float, table: tuple[np.ndarray, np.ndarray]) -> float:
    """Variance (DN^2) from squared residuals ``u`` (noise, plus texture and edges in a minority).

    The mean of ``u`` below ``clip_sigma^2`` times the variance, corrected for the clip and
    iterated. A mean, not a quantile: residuals of integer readings
    take discrete values where the signal barely varies, and a quantile of those jumps.
    """
    # start from above (the mean of all but the top percent) and clip down to the fixed point: from
    # below, integer residuals of small noise (mostly 0 and +-1) would stop the clip short
    median, top = _median_and_quantile(u, 0.99)
    v = max(_variance_from_median(median, table), float(np.mean(u[u <= top])))
    corr = _clip_correction(clip_sigma)
    count = -1
    for _ in range(6):
        inside = u <= clip_sigma * clip_sigma * v
        kept = int(np.count_nonzero(inside))
        if kept == 0 or kept == count:  # the same samples as the last pass: converged
            break
        count = kept
        v = float(np.dot(u, inside)) / kept / corr
    return v


def _bin_index(t: np.ndarray, bins: int) -> tuple[np.ndarray, np.ndarray]:
    """The bin of every sample, int64 (N,), bins equally spaced in log(t + 2 DN) over the samples' range,
    and the bin edges in t, float64 (bins + 1,)."""
    coord = np.log(np.maximum(t, 0.0) + 2.0)
    lo, hi = float(coord.min()), float(coord.max())
    which = np.minimum(((coord - lo) / max(hi - lo, 1e-9) * bins).astype(np.int64), bins - 1)
    return which, np.exp(np.linspace(lo, hi, bins + 1)) - 2.0


def bin_samples(samples: NoiseSamples, config: EstimatorConfig, *,
                temporal: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Signal bins, equally spaced in log(t + 2 DN): (mean t, robust variance, count), float64/float64/int64 (B,).

    The variance of a bin is read from the median of its squared residuals (half the samples may
    be texture or edges without moving it), through the rounded-Gaussian table; bins with fewer
    than ``config.min_bin`` samples are left out. ``temporal`` (samples that hold no texture): clipped
    at ``config.temporal_clip_sigma``, and the count is the effective one, ``2 v^2 / var(u)`` times the
    count, so that the fit's Gaussian weights give the bin's measured standard error (shot noise of a
    few electrons is heavier-tailed than a Gaussian, and its variance estimates scatter more).
    """
    if temporal:
        config = replace(config, clip_sigma=config.temporal_clip_sigma)
    if samples.size < config.min_bin:
        return np.zeros(0), np.zeros(0), np.zeros(0, np.int64)
    table = _median_table()
    which, _ = _bin_index(samples.t, config.bins)
    order = np.argsort(which, kind="stable")
    counts = np.bincount(which, minlength=config.bins)
    starts = np.concatenate([[0], np.cumsum(counts)])
    t, v, c = [], [], []
    for k in range(config.bins):
        if counts[k] < config.min_bin:
            continue
        idx = order[starts[k]:starts[k + 1]]
        t.append(float(np.mean(samples.t[idx])))
        v.append(_robust_variance(samples.u[idx], config.clip_sigma, table))
        count = int(counts[k])
        if temporal:
            u = samples.u[idx]
            u = u[u <= config.clip_sigma**2 * v[-1]]
            spread = float(np.var(u)) if u.size > 1 else 0.0
            count = int(min(count, max(2.0 * v[-1] ** 2 * u.size / spread, 1.0))) if spread > 0 else count
        c.append(count)
    return np.array(t), np.array(v), np.array(c, np.int64)


def fit_line(t: np.ndarray, v: np.ndarray, n: np.ndarray, *, slope: float | None = None,
             intercept: float | None = None, outlier_tolerance: float = 0.1,
             texture: bool = False) -> LineFit | None:
    """Weighted least squares of ``v = slope * t + intercept`` over bins, dropping bins well above the line.

    Each bin weighs ``n / (2 model^2)`` (a variance estimate's variance is ``2 v^2 / n``). A bin
    more than ``outlier_tolerance`` plus three standard errors above the line is dropped (texture only
    inflates); one far below (four standard errors and the tolerance) too. A given ``slope`` or
    ``intercept`` is held fixed. With ``texture`` a term ``k t^2`` (``k >= 0``) is fitted too and
    left out of the noise: texture that survives the flatness tests is a contrast, its variance
    grows as the signal squared where shot noise grows as the signal (``LineFit.texture`` is ``k``;
    the covariance of slope and intercept then includes what not knowing ``k`` costs).
    None when fewer than 2 bins (3 for both free) remain or the slope is not positive.
    """
    t, v, n = (np.asarray(a, np.float64) for a in (t, v, n))
    free = [slope is None, intercept is None]
    need = 1 + sum(free)
    if t.size < need:
        return None
    quad = texture and free[0] and t.size >= need + 2
    inlier = np.ones(t.size, bool)
    model = np.maximum(v, QUANTISATION_VARIANCE)
    coef = np.array([slope or 0.0, intercept or 0.0, 0.0])
    cov = np.zeros((2, 2))

    def design(with_quad: bool) -> np.ndarray:
        cols = [c for c, f in zip((t, np.ones_like(t)), free) if f] + ([t * t] if with_quad else [])
        return np.stack(cols, axis=1)

    def solve(w: np.ndarray) -> tuple[np.ndarray, bool]:
        target = v - (0.0 if slope is None else slope * t) - (0.0 if intercept is None else intercept)
        for with_quad in ((True, False) if quad else (False,)):
            sol, *_ = np.linalg.lstsq(design(with_quad) * w[:, None], target * w, rcond=None)
            if not with_quad or sol[-1] >= 0:
                break
        k = 0
        out = np.array([slope or 0.0, intercept or 0.0, 0.0])
        for j, f in enumerate(free):
            if f:
                out[j] = sol[k]
                k += 1
        if with_quad:
            out[2] = sol[-1]
        return out, with_quad

    used_quad = False
    for _ in range(8):
        w = np.sqrt(n / 2.0) / model * inlier
        if int(inlier.sum()) < need + used_quad:
            return None
        coef, used_quad = solve(w)
        model_new = np.maximum(coef[0] * t + coef[1] + coef[2] * t * t, QUANTISATION_VARIANCE)
        se = model_new * np.sqrt(2.0 / n)
        new_inlier = ((v <= model_new * (1 + outlier_tolerance) + 3 * se)
                      & (v >= model_new * (1 - outlier_tolerance) - 4 * se))
        converged = np.array_equal(new_inlier, inlier) and np.allclose(model_new, model, rtol=1e-4)
        model, inlier = model_new, new_inlier
        if converged:
            break
        if int(inlier.sum()) < need + used_quad:
            return None
    w = np.sqrt(n / 2.0) / model * inlier
    a = design(used_quad) * w[:, None]
    dof = max(int(inlier.sum()) - need - used_quad, 1)
    resid = (v - model) * w
    chi2 = float(np.sum(resid * resid)) / dof
    try:
        sub = np.linalg.inv(a.T @ a) * max(chi2, 1.0)
    except np.linalg.LinAlgError:
        return None
    idx = [k for k, f in enumerate(free) if f]
    for i, ki in enumerate(idx):
        for j, kj in enumerate(idx):
            cov[ki, kj] = sub[i, j]
    if not coef[0] > 0:
        return None
    texture_sigma = math.sqrt(max(float(sub[-1, -1]), 0.0)) if used_quad else 0.0
    return LineFit(float(coef[0]), float(coef[1]), cov, t, v, n.astype(np.int64), inlier, not free[0],
                   float(coef[2]), texture_sigma)
