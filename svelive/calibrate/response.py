"""The camera's response function from one SVE frame (paper section 8; Mitsunaga and Nayar 1999).

Brightness ``M`` (raw minus black, divided by white minus black: 0..1) relates to
scaled linear radiance ``I`` by the inverse response ``I = f(M) = sum c_n M^n``,
normalised by ``f(1) = 1``. Neighbouring pixels of an SVE frame see the scene
with known exposure ratios, so where the scene is locally constant the means of
the exposure sub-images over a small window obey ``f(M_l) = R_lk f(M_k)``,
``R_lk = e_l / e_k``: a linear least-squares problem in the ``c_n``.

Steps (:func:`fit_response`):

1. Per exposure level, mean and variance of its readings over windows of
   ``window`` x ``window`` tiles; windows with a clipped reading are dropped.
2. The noise variance at each brightness is measured from the frame itself
   (:func:`svelive.calibrate.noise.noise_curve_frame`); a window is "locally
   constant" when its variance is what noise alone would give at the
   ``flat_quantile`` level of a chi-square test.
3. Every pair of flat levels at a location gives ``f(M_hi) / R - f(M_lo) = 0``,
   normalised by the window values' noise (including the rounding bias a
   constant window shares) propagated through ``f'`` of the previous pass.
   The curve's shape is solved scale-free in a Legendre basis on [0, 1] (the
   smallest generalised eigenvector of the normalised residuals against the
   equations' scale), then scaled to ``f(1) = 1``: imposing ``f(1) = 1`` inside
   the least squares drifts where ``M = 1`` has no data.
4. The degree is the lowest one whose error on held-out locations (spatial
   folds, so held-out windows do not share pixels with training ones) is within
   one standard error of the best degree's (the one-standard-error rule), among
   degrees whose curve is monotone on the measured range.
5. The measured range is the longest brightness interval with data in every
   1/16 of full scale and a standard error of ``f`` (from the fit's covariance)
   under 1 %: gaps in the data end it.
6. For sweeps without a common exposure ratio (``max_knots``, on by default) a log-spline
   competes with the polynomials: ``log f`` a natural cubic spline in ``log M`` with
   ``max_knots`` knots evenly spaced in logit(M) over the data (a power law above the top
   of the data, up to white), fitted by least squares on ``log f(M_hi) - log f(M_lo) =
   log R`` (:func:`_solve_spline`), and a power law (2 knots); the same held-out rule
   chooses among them and the degrees, on the equations whose darker value rounding cannot
   move by more than 1 % (:func:`_undithered` has why). The splines also maximise the likelihood
   of which pixels reach white in a brighter frame given their reading in a darker one (a probit,
   :func:`_censored_with_pilot`): that pins the curve at white, hence its scale, with no window
   selected on its pixels' texture. On by default for sweeps (:data:`SWEEP_KNOTS`; see the docs).
7. Optionally (``refine_ratios``) the exposure ratios are re-estimated from the
   fitted curve and the fit repeated; the ratio of the extreme exposures is kept
   at its nominal value because ``f^g`` with ratios ``R^g`` fits the same data
   for any ``g`` (the exponential ambiguity of ratio-based calibration).
docs/calibration.md has the details and the measured accuracy.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
from numpy.polynomial import legendre as L
from numpy.polynomial import polynomial as P

from svelive.calibrate.noise import QUANTISATION_VARIANCE, _chi2_quantile, noise_curve_frame
from svelive.core.atomic import write_bytes_atomic
from svelive.core.errors import SveliveError
from svelive.core.pattern import Pattern
from svelive.core.response import Response, _log_spline_value, log_spline_basis
from svelive.core.sensor import Sensor

#: knots of the log-spline a sweep's fit is offered by default (ResponseFitConfig.max_knots): held-out error
#: flattens from about 6 knots on, and 12 follow a film's toe and shoulder (docs/calibration.md)
SWEEP_KNOTS = 12


@dataclass(frozen=True)
class ResponseFitConfig:
    """Options of :func:`fit_response`.

    Attributes:
        max_degree: highest polynomial degree tried (1..10).
        window: side of the local window, in tiles (odd, >= 3).
        flat_quantile: a window is flat when its variance is below this quantile
            of what noise alone would give.
        folds: number of spatial folds for the held-out degree choice.
        fold_block: side, in windows, of the square blocks assigned to one fold.
        min_locations: fewest flat locations with two or more usable exposures.
        min_span: least width of the measured brightness range.
        refine_ratios: re-estimate the intermediate exposure ratios from the data.
        max_uncertainty: largest standard error of the fitted curve (fraction of full
            scale) inside the measured range.
        coverage_bins, coverage_count: the measured range is made of brightness bins
            (``coverage_bins`` over [0, 1]) each holding at least ``coverage_count``
            ends of equations; a gap in the data ends it.
        seed: seed of the fold assignment.
        max_equations: with several frames, locations are left out at random beyond this
            many ratio equations (time and memory grow with them; one frame is never cut).
        max_knots: knots of the log-spline model (:data:`SWEEP_KNOTS` by default; below 2: none, the
            polynomials alone), offered with that many knots and as a power law (2 knots), which then
            compete with the polynomials by held-out error on sweeps without a common exposure ratio
            (never on one frame). With it, sweeps recover S-shaped curves within 1 % at 8 and 12 bits on
            the benchmark's photographs (0.6-6.5 % with polynomials alone), and a gamma camera on a
            narrow range (BrightRings) within 0.06 % (3.5-10.4 %); it moves polynomial cameras' fits by
            up to 0.05 % (docs/calibration.md).
        dark_snr: when the log-spline is offered, equations whose darker window value is under
            this many single-reading noise standard deviations are left out (for every model).
        rounding_tolerance: when the log-spline is offered, the held-out errors that choose among the
            models count only equations whose darker value is at least half a quantisation step divided
            by this (0.01: 50 DN): there rounding, whatever the noise, moves it by less than this
            fraction. Rounding leaves an error that every window of one brightness shares, which a
            flexible model follows and held-out locations (sharing it) cannot reveal.
    """

    max_degree: int = 6
    window: int = 3
    flat_quantile: float = 0.95
    folds: int = 5
    fold_block: int = 8
    min_locations: int = 100
    min_span: float = 0.3
    refine_ratios: bool = False
    max_uncertainty: float = 0.01
    coverage_bins: int = 16
    coverage_count: int = 1
    seed: int = 0
    max_equations: int = 250_000
    max_knots: int = SWEEP_KNOTS
    dark_snr: float = 3.0
    rounding_tolerance: float = 0.01


@dataclass(frozen=True)
class _Pairs:
    """Ratio equations f(m_hi) - R f(m_lo) = 0 of flat locations (one entry per level pair)."""

    m_lo: np.ndarray      # float64 (P,), normalised brightness of the lower exposure
    m_hi: np.ndarray      # float64 (P,)
    var_lo: np.ndarray    # float64 (P,), variance of m_lo (a window mean)
    var_hi: np.ndarray
    k_lo: np.ndarray      # int (P,), level index of the lower exposure
    k_hi: np.ndarray
    location: np.ndarray  # int (P,), index of the location
    fold: np.ndarray      # int (P,), spatial fold of the location
    noise_lo: np.ndarray  # float64 (P,), analog noise sd of one reading at m_lo (DN, quantisation excluded)
    noise_hi: np.ndarray


@dataclass(frozen=True)
class _Censored:
    """Same-pixel evidence at white from a sweep: per raw code of a reading in a darker frame, how many
    of those pixels read at white in a brighter frame (one row per code and pair of frames).

    A reading at white says only that the pixel's light reached the white threshold, and the same
    pixel's reading in the darker frame says how much light that pixel had: no texture and no window
    selection come in, so these rows pin the curve's value at white against its value at the darker
    readings (the scale of the whole curve) without the windows that white removes.
    """

    m: np.ndarray          # float64 (C,), brightness of the darker reading
    log_ratio: np.ndarray  # float64 (C,), log of the brighter frame's exposure over the darker's
    total: np.ndarray      # float64 (C,), pixels with that reading
    clipped: np.ndarray    # float64 (C,), of them, those at white in the brighter frame
    pair: np.ndarray       # int (C,), index of the pair of frames (0..pairs - 1)
    threshold: float       # brightness from which a reading rounds to white
    width: np.ndarray | None = None  # float64 (C,), sd of the probit in log light (both readings' noise)


def _window_sums(sub: np.ndarray, window: int) -> np.ndarray:
    """Sum over window x window neighbourhoods, valid part only, float64."""
    s = cv2.boxFilter(sub, cv2.CV_64F, (window, window), normalize=False, borderType=cv2.BORDER_CONSTANT)
    r = window // 2
    return s[r:s.shape[0] - r, r:s.shape[1] - r]


def level_window_statistics(raw: np.ndarray, pattern: Pattern, sensor: Sensor, window: int):
    """Per exposure level, a plane fitted to its readings over windows of ``window`` x ``window`` tiles.

    Within a window the readings of one level are fitted by ``M = a + b_y dy + b_x dx``
    (dy, dx in pixels from the window's centre, the same point for every level),
    so the levels are compared at one point even though their pixels are offset
    and the scene has a gradient there.

    Returns (value, residual_var, var_factor, count, usable): value = a, the
    level's brightness at the centre, and residual_var, the variance of the
    readings about the plane (n - 3 degrees of freedom), both float64 (K, Y, X)
    with Y x X window positions, one per tile; var_factor (K,) turns one reading's
    variance into the variance of ``value``; count (K,) readings per window;
    usable bool (K, Y, X): no reading in the window is clipped at 0 or at white.
    """
    th, tw = pattern.shape
    ny, nx = raw.shape[0] // th, raw.shape[1] // tw
    if ny < window or nx < window:
        raise SveliveError(f"frame {raw.shape[1]}x{raw.shape[0]} holds fewer than {window}x{window} tiles of {tw}x{th}")
    x = raw[:ny * th, :nx * tw].astype(np.float64)
    scale = 1.0 / sensor.range_dn
    level_idx = np.searchsorted(pattern.levels, pattern.tile)
    K = pattern.levels.size
    r = window // 2
    out_shape = (ny - 2 * r, nx - 2 * r)
    # window centre tile index of every output position, and tile offsets within a window
    ci = np.arange(r, ny - r, dtype=np.float64)[:, None]
    cj = np.arange(r, nx - r, dtype=np.float64)[None, :]
    offsets = np.arange(-r, r + 1, dtype=np.float64)
    b = np.zeros((K, 3) + out_shape)
    s2 = np.zeros((K,) + out_shape)
    G = np.zeros((K, 3, 3))
    clipped = np.zeros((K,) + out_shape)
    count = np.zeros(K, dtype=np.int64)
    jj, ii = np.meshgrid(np.arange(nx, dtype=np.float64), np.arange(ny, dtype=np.float64))
    for a in range(th):
        for c in range(tw):
            k = level_idx[a, c]
            sub = x[a::th, c::tw]
            m = (sub - sensor.black_level) * scale
            sum_m = _window_sums(m, window)
            oy, ox = a - (th - 1) / 2.0, c - (tw - 1) / 2.0
            # sum of m * dy with dy = (row - centre row) * th + oy, likewise dx
            b[k, 0] += sum_m
            b[k, 1] += th * (_window_sums(m * ii, window) - ci * sum_m) + oy * sum_m
            b[k, 2] += tw * (_window_sums(m * jj, window) - cj * sum_m) + ox * sum_m
            s2[k] += _window_sums(m * m, window)
            dy = (th * offsets + oy)[:, None] * np.ones(window)[None, :]
            dx = np.ones(window)[:, None] * (tw * offsets + ox)[None, :]
            basis = np.stack([np.ones_like(dy), dy, dx]).reshape(3, -1)
            G[k] += basis @ basis.T
            clipped[k] += _window_sums(((sub <= 0) | (sub >= sensor.white_level)).astype(np.float64), window)
            count[k] += window * window
    value = np.zeros((K,) + out_shape)
    residual_var = np.zeros((K,) + out_shape)
    var_factor = np.zeros(K)
    for k in range(K):
        G_inv = np.linalg.inv(G[k])
        coef = np.einsum("ij,j...->i...", G_inv, b[k])
        value[k] = coef[0]
        rss = s2[k] - np.einsum("i...,i...->...", coef, b[k])
        residual_var[k] = np.maximum(rss, 0.0) / (count[k] - 3)
        var_factor[k] = G_inv[0, 0]
    return value, residual_var, var_factor, count, clipped == 0


def _noise_variance_fn(raw: np.ndarray, pattern: Pattern, sensor: Sensor) -> Callable[[np.ndarray], np.ndarray]:
    """Noise variance of one reading in normalised brightness, as a function of brightness."""
    curve = noise_curve_frame(raw, pattern, sensor)
    r = sensor.range_dn
    floor = QUANTISATION_VARIANCE / r**2
    sig = curve.signal / r
    var = np.maximum(curve.variance / r**2, floor)
    return lambda m: np.interp(m, sig, var)


def quantisation_bias_variance(sigma_dn: np.ndarray) -> np.ndarray:
    """Variance (DN^2) of the expected rounding error of a reading whose analog noise is ``sigma_dn`` DN.

    Rounding to integers adds the error e(x) = x - round(x); averaged over the noise
    its expectation is sum_k (-1)^(k+1) sin(2 pi k x) exp(-2 pi^2 k^2 sigma^2) / (pi k),
    whose variance over x is sum_k exp(-4 pi^2 k^2 sigma^2) / (2 pi^2 k^2): 1/12 without
    noise, negligible above about 0.5 DN. This part is the same for every reading of a
    constant area, so averaging a window does not reduce it.
    """
    k = np.arange(1, 9, dtype=np.float64)
    s2 = np.asarray(sigma_dn, np.float64)[..., None] ** 2
    return np.sum(np.exp(-4.0 * np.pi**2 * k**2 * s2) / (2.0 * np.pi**2 * k**2), axis=-1)


def _window_mean_variance(reading_var: np.ndarray, var_factor: float, range_dn: float) -> np.ndarray:
    """Variance of a level's window value (normalised brightness^2) from one reading's variance.

    The analog noise and the independent part of the rounding error average down by
    ``var_factor``; the rounding bias shared by a constant window does not.
    """
    q = QUANTISATION_VARIANCE
    var_dn = reading_var * range_dn**2
    bias = quantisation_bias_variance(np.sqrt(np.maximum(var_dn - q, 0.0)))
    return ((var_dn - bias) * var_factor + bias) / range_dn**2


def _undithered(pairs: _Pairs, range_dn: float) -> _Pairs:
    """``pairs`` with the window values' shared rounding variance at its undithered value, 1/12 DN^2.

    :func:`_window_mean_variance` lets the noise dither the rounding, with the noise of the frame's
    own noise curve; from one photographed frame that curve reads high (texture looks like noise),
    so it can declare dithered a dark window whose readings all round alike. The worst case
    instead: the error of a value a few DN above black then weighs as the step it can be.
    """
    extra_lo = (QUANTISATION_VARIANCE - quantisation_bias_variance(pairs.noise_lo)) / range_dn**2
    extra_hi = (QUANTISATION_VARIANCE - quantisation_bias_variance(pairs.noise_hi)) / range_dn**2
    return replace(pairs, var_lo=pairs.var_lo + extra_lo, var_hi=pairs.var_hi + extra_hi)


def _too_few(found: int, needed: int) -> str:
    return (f"only {found} locally constant regions show two or more exposures unclipped (need {needed}): "
            "use a frame of a still scene with large smooth areas (walls, sky, a grey card) from dark to "
            "bright, exposed so that the lowest exposure is not saturated")


def _flat_levels(raw: np.ndarray, pattern: Pattern, sensor: Sensor, cfg: ResponseFitConfig,
                 statistics: tuple) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(variance of each level's window value float64 (K, Y, X), flat bool (K, Y, X), analog noise sd
    of one reading in DN float64 (K, Y, X)) of one frame from its :func:`level_window_statistics`:
    flat windows are unclipped and pass the chi-square test against the frame's own noise curve."""
    mean, var, var_factor, count, usable = statistics
    noise_var = _noise_variance_fn(raw, pattern, sensor)
    flat = np.zeros_like(usable)
    var_mean = np.zeros_like(mean)
    analog = np.zeros_like(mean)
    for k in range(mean.shape[0]):
        dof = int(count[k]) - 3
        limit = _chi2_quantile(cfg.flat_quantile, dof) / dof
        nv = noise_var(mean[k])
        flat[k] = usable[k] & (var[k] <= nv * limit)
        var_mean[k] = _window_mean_variance(nv, var_factor[k], sensor.range_dn)
        analog[k] = np.sqrt(np.maximum(nv * sensor.range_dn**2 - QUANTISATION_VARIANCE, 0.0))
    return var_mean, flat, analog


def _collect_pairs(raws: np.ndarray | list[np.ndarray], pattern: Pattern, sensor: Sensor, cfg: ResponseFitConfig,
                   exposures: np.ndarray | None = None,
                   progress: Callable[[str], None] | None = None) -> _Pairs:
    """Ratio equations between every two flat levels at a location, over all frames.

    Args:
        raws: one (H, W) frame or a list of frames of the same still scene (same shape).
        exposures: (J K,) exposure of every (frame j, level k), frame-major (index j K + k);
            None: the pattern's levels (one frame). Levels of equal exposure give no equation.
    """
    raws = [raws] if isinstance(raws, np.ndarray) else list(raws)
    if exposures is None:
        exposures = pattern.levels.astype(np.float64)
    statistics = []
    for j, raw in enumerate(raws):
        if progress is not None and len(raws) > 1:
            progress(f"frame {j + 1}/{len(raws)}: window statistics")
        statistics.append(level_window_statistics(raw, pattern, sensor, cfg.window))
    usable = np.concatenate([st[4] for st in statistics])
    unclipped = int(np.sum(usable.sum(axis=0) >= 2))
    if unclipped < cfg.min_locations:
        raise SveliveError(_too_few(unclipped, cfg.min_locations))
    if progress is not None:
        progress("noise curve and constant regions")
    flat_parts = [_flat_levels(raw, pattern, sensor, cfg, st) for raw, st in zip(raws, statistics)]
    mean = np.concatenate([st[0] for st in statistics])
    var_mean = np.concatenate([fp[0] for fp in flat_parts])
    flat = np.concatenate([fp[1] for fp in flat_parts])
    analog = np.concatenate([fp[2] for fp in flat_parts])
    del statistics, flat_parts, usable
    V = mean.shape[0]
    Y, X = mean.shape[1:]
    loc = np.arange(Y * X).reshape(Y, X)
    rng = np.random.default_rng(cfg.seed)
    by, bx = -(-Y // cfg.fold_block), -(-X // cfg.fold_block)
    block_fold = rng.permutation(by * bx) % cfg.folds
    yy, xx = np.mgrid[0:Y, 0:X]
    fold = block_fold[(yy // cfg.fold_block) * bx + xx // cfg.fold_block]
    pairs = [(a, b) if exposures[a] < exposures[b] else (b, a)
             for a in range(V) for b in range(a + 1, V) if exposures[a] != exposures[b]]
    keep = np.ones((Y, X), bool)
    if len(raws) > 1:
        # a sweep multiplies the equations (every level of every frame against every other): beyond
        # ``max_equations`` whole locations are left out at random, which costs precision, not coverage
        total = sum(int(np.count_nonzero(flat[lo] & flat[hi])) for lo, hi in pairs)
        if total > cfg.max_equations:
            keep = rng.random((Y, X)) < cfg.max_equations / total
    parts = []
    for lo, hi in pairs:
        sel = flat[lo] & flat[hi] & keep
        parts.append((mean[lo][sel], mean[hi][sel], var_mean[lo][sel], var_mean[hi][sel],
                      np.full(sel.sum(), lo), np.full(sel.sum(), hi), loc[sel], fold[sel],
                      analog[lo][sel], analog[hi][sel]))
    cols = [np.concatenate([p[i] for p in parts]) for i in range(10)]
    return _Pairs(*cols)


def _censored_at_white(raws: list[np.ndarray], times: np.ndarray, sensor: Sensor) -> _Censored:
    """:class:`_Censored` rows of every two frames of a sweep (the darker reading strictly between black
    and white; every pixel, whatever its neighbours, since both readings are of the same pixel).

    Args:
        raws: J (H, W) frames of one still scene.
        times: (J,) their exposure times.
    """
    white = float(sensor.white_level)
    black = float(sensor.black_level)
    # the ADC rounds: a reading is at white from half a step under it
    threshold = 1.0 - 0.5 / sensor.range_dn
    parts = []
    for j, k in _frame_pairs(times):
        dark, bright = raws[j].ravel(), raws[k].ravel()
        inside = (dark > black) & (dark < white)
        codes = dark[inside].astype(np.int64)
        total = np.bincount(codes, minlength=int(white) + 1).astype(np.float64)
        clipped = np.bincount(codes, weights=(bright[inside] >= white).astype(np.float64), minlength=total.size)
        code = np.nonzero(total)[0]
        parts.append(((code - black) / sensor.range_dn, np.full(code.size, math.log(times[k] / times[j])),
                      total[code], clipped[code], np.full(code.size, len(parts))))
    cols = [np.concatenate([p[i] for p in parts]) for i in range(5)]
    return _Censored(*cols[:4], cols[4].astype(np.int64), threshold=threshold)


def _probit_sides(z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(log Phi(z), log Phi(-z), phi(z) / Phi(z), phi(z) / Phi(-z)) of the standard normal, float64 like
    ``z``; accurate in both tails (the smaller side from erfc), clipped at |z| = 35."""
    z = np.clip(np.asarray(z, np.float64), -35.0, 35.0)
    tail = 0.5 * np.vectorize(math.erfc, otypes=[np.float64])(np.abs(z) / math.sqrt(2.0))
    low, high = np.where(z < 0, tail, 1.0 - tail), np.where(z < 0, 1.0 - tail, tail)
    density = np.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi)
    return np.log(low), np.log(high), density / low, density / high


def _probit_newton(predictor: Callable[[np.ndarray], np.ndarray], rows: np.ndarray, start: np.ndarray,
                   total: np.ndarray, hits: np.ndarray, quadratic: tuple[np.ndarray, np.ndarray, float] | None = None,
                   steps: int = 50) -> np.ndarray:
    """Minimise ``-2 log L(p) (+ p'Np - 2 p'r + c)`` by Newton's method, L the probit likelihood of ``hits``
    out of ``total`` with ``z = predictor(p)`` linear in p with rows ``rows`` (C, n) (so z = rows @ p +
    const); ``quadratic`` = (N, r, c) of a least-squares term. Convex.

    Returns p.
    """
    normal, rhs, constant = quadratic if quadratic is not None else (np.zeros((start.size,) * 2),
                                                                      np.zeros(start.size), 0.0)

    def objective(p: np.ndarray) -> float:
        up, down, _, _ = _probit_sides(predictor(p))
        return float(p @ normal @ p - 2.0 * p @ rhs + constant - 2.0 * np.sum(hits * up + (total - hits) * down))

    p = start.copy()
    value = objective(p)
    for _ in range(steps):
        z = predictor(p)
        _, _, up, down = _probit_sides(z)
        slope = -hits * up + (total - hits) * down
        curvature = hits * up * (z + up) + (total - hits) * down * (down - z)
        gradient = 2.0 * (normal @ p - rhs) + 2.0 * rows.T @ slope
        hessian = 2.0 * normal + 2.0 * (rows.T * curvature) @ rows
        # no ridge: the weakest direction (the scale, eigenvalue ~1e-12 of the largest) is the one that matters
        step = np.linalg.lstsq(hessian, gradient, rcond=None)[0]
        if gradient @ step < 1e-9:  # Newton decrement: the objective (a chi-square) cannot fall further
            break
        t = 1.0
        while t > 1e-6:
            trial = objective(p - t * step)
            if trial <= value:
                break
            t *= 0.5
        else:
            break
        p, value = p - t * step, trial
    return p


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


def _frame_pairs(times: np.ndarray) -> list[tuple[int, int]]:
    """(darker, brighter) frame indices of every two frames of a sweep with different exposure times."""
    return [(a, b) for a in range(len(times)) for b in range(len(times)) if times[a] < times[b]]


def _design(pairs: _Pairs, exposures: np.ndarray, degree: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows of f(m_hi) / R - f(m_lo) = 0 with c_0 eliminated by f(1) = 1: A c_{1..N} = y."""
    inv_r = exposures[pairs.k_lo] / exposures[pairs.k_hi]
    n = np.arange(1, degree + 1)
    A = (pairs.m_hi[:, None] ** n - 1.0) * inv_r[:, None] - (pairs.m_lo[:, None] ** n - 1.0)
    y = inv_r - 1.0
    return A, -y


def _coefficients(c_rest: np.ndarray) -> np.ndarray:
    return np.concatenate([[1.0 - c_rest.sum()], c_rest])


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


def _subset(pairs: _Pairs, sel) -> _Pairs:
    return _Pairs(*(getattr(pairs, f)[sel] for f in pairs.__dataclass_fields__))


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


def _refine_exposures(pairs: _Pairs, exposures: np.ndarray, curve: Response) -> np.ndarray:
    """Exposures re-estimated from f(m_hi) / f(m_lo), with the extreme ratio kept nominal."""
    f_lo, f_hi = curve(pairs.m_lo), curve(pairs.m_hi)
    ok = (f_lo > 0.01) & (f_hi > 0.01)
    K = exposures.size
    if not ok.any():
        return exposures
    # log e_hi - log e_lo = log(f_hi / f_lo), least squares with log e_0 fixed
    A = np.zeros((int(ok.sum()), K))
    rows = np.arange(A.shape[0])
    A[rows, pairs.k_hi[ok]] += 1.0
    A[rows, pairs.k_lo[ok]] -= 1.0
    b = np.log(f_hi[ok] / f_lo[ok])
    observed = np.unique(np.concatenate([pairs.k_lo[ok], pairs.k_hi[ok]]))
    if 0 not in observed or K - 1 not in observed:
        return exposures
    log_e, *_ = np.linalg.lstsq(A[:, 1:], b, rcond=None)
    log_e = np.concatenate([[0.0], log_e])
    nominal = np.log(exposures / exposures[0])
    if not log_e[-1] > 0:
        return exposures
    log_e *= nominal[-1] / log_e[-1]
    return exposures[0] * np.exp(log_e)


def common_ratio(exposures: np.ndarray, max_power: int = 12, tolerance: float = 1e-3) -> float | None:
    """The ratio R of which every exposure ratio is an integer power, or None when there is none.

    Ratio equations then hold equally for ``f`` and for ``f(M) p(log_R f(M))`` with
    any p periodic of period 1 (a log-periodic ripple), so one frame cannot tell
    them apart: only the polynomial model does, well for curves a low-degree
    polynomial follows, by several % for S-shaped film curves (docs/calibration.md).
    Two exposure levels always have one. Found as the largest R = r^(1/k),
    r the smallest ratio and k <= ``max_power``, whose powers give every ratio
    within ``tolerance`` (relative, in the logarithm).

    Args:
        exposures: (N,) positive exposure levels, any order.
    """
    logs = np.log(np.unique(np.asarray(exposures, np.float64)))
    steps = logs[1:] - logs[0]
    if steps.size == 0:
        return None
    for k in range(1, max_power + 1):
        unit = steps[0] / k
        powers = steps / unit
        if np.all(np.abs(powers - np.round(powers)) <= tolerance * np.maximum(powers, 1.0)):
            return float(f"{np.exp(unit):.6g}")
    return None


def _check_frames(raw: np.ndarray | list[np.ndarray], exposure_times) -> tuple[list[np.ndarray], np.ndarray]:
    """The frames as a list and their exposure times (float64 (J,), ones for a single frame)."""
    raws = [np.asarray(raw)] if isinstance(raw, np.ndarray) else [np.asarray(r) for r in raw]
    if not raws:
        raise SveliveError("response calibration needs at least one frame")
    for i, r in enumerate(raws):
        which = "raw frame" if len(raws) == 1 else f"frame {i + 1}"
        if r.ndim != 2 or r.size == 0:
            raise SveliveError(f"{which} must be a non-empty single-channel 2-D array, got shape {r.shape}")
        if r.dtype.kind not in "ui":
            raise SveliveError(f"response calibration takes the camera's integer raw values, got {r.dtype}")
        if r.shape != raws[0].shape:
            raise SveliveError(f"frame {i + 1} is {r.shape[1]}x{r.shape[0]}, frame 1 "
                               f"{raws[0].shape[1]}x{raws[0].shape[0]}: give frames of one camera and region")
    if exposure_times is None:
        if len(raws) > 1:
            raise SveliveError(f"{len(raws)} frames need their exposure times (--exposure-times T1,T2,...)")
        return raws, np.ones(1)
    times = np.asarray(exposure_times, np.float64).ravel()
    if times.size != len(raws):
        raise SveliveError(f"{times.size} exposure times for {len(raws)} frames: give one per frame")
    if not np.all(np.isfinite(times) & (times > 0)):
        raise SveliveError(f"exposure times must be positive numbers, got {times.tolist()}")
    return raws, times


def fit_response(raw: np.ndarray | list[np.ndarray], pattern: Pattern | str, sensor: Sensor,
                 config: ResponseFitConfig = ResponseFitConfig(), *, exposure_times=None,
                 progress: Callable[[str], None] | None = None) -> Response:
    """Fit the inverse response polynomial to one raw SVE frame, or to frames at several global exposures.

    With several frames of the same still scene taken at global exposure times
    ``t_j``, every (frame j, level k) is one exposure ``t_j e_k``: the ratio
    equations within each frame and between every two frames enter one fit with
    their noise weights. Exposure ratios that are not powers of the pattern's
    ratio remove the log-periodic ambiguity of one frame (:func:`common_ratio`).

    Args:
        raw: (H, W) uint8/uint16 raw frame, DN including black, of a static scene
            with smooth areas spanning dark to bright; or a list of such frames.
        pattern: the exposure pattern with its nominal exposures.
        sensor: bit depth, black and white level.
        config: fit options.
        exposure_times: (J,) global exposure time of every frame, any unit (needed
            for more than one frame).
        progress: called with a short text at each stage (e.g. for a progress line).

    Returns:
        The Response; ``stats`` holds the measured brightness range, the number of
        locations and equations, the held-out error of every degree tried, the
        exposures used and the uncertainty band over the measured range.
    """
    raws, times = _check_frames(raw, exposure_times)
    if not 1 <= config.max_degree <= 10:
        raise SveliveError(f"max degree must be 1..10, got {config.max_degree}")
    if not 0 <= config.max_knots <= 16:
        raise SveliveError(f"max knots must be 0..16 (0: polynomials only), got {config.max_knots}")
    if config.window < 3 or config.window % 2 == 0:
        raise SveliveError(f"window must be odd and >= 3 tiles, got {config.window}")
    pattern = Pattern.parse(pattern)
    if pattern.levels.size < 2 and len(raws) < 2:
        raise SveliveError("the pattern has one exposure only; response calibration needs two or more")
    nominal = (times[:, None] / times[0] * pattern.levels.astype(np.float64)[None, :]).ravel()
    pairs = _collect_pairs(raws, pattern, sensor, config, nominal, progress)
    n_locations = int(np.unique(pairs.location).size)
    if n_locations < config.min_locations:
        raise SveliveError(_too_few(n_locations, config.min_locations))
    # any increasing response reads a brighter value at the higher exposure; on data that is not an
    # SVE frame of this pattern (wrong pattern, pure texture or noise) that fails at many locations
    lit = pairs.m_hi > 3.0 * np.sqrt(pairs.var_hi)
    flipped = float(np.mean(pairs.m_hi[lit] <= pairs.m_lo[lit])) if lit.any() else 0.0
    if flipped > 0.1:
        raise SveliveError(
            f"at {flipped:.0%} of the constant regions the higher exposure reads darker than the lower one: "
            + ("this is not an SVE frame of this pattern (check --pattern and the tile origin) or the scene moved"
               if len(raws) == 1 else "check --pattern, the order of the exposure times, and that the scene "
               "and camera stood still"))
    used = np.concatenate([pairs.m_lo, pairs.m_hi])
    measured = (float(np.min(used)), float(np.max(used)))
    if measured[1] - measured[0] < config.min_span:
        raise SveliveError(
            f"the constant regions only cover brightness {measured[0]:.2f}..{measured[1]:.2f} of full scale "
            f"(need a span of {config.min_span:.2f}): use a scene with smooth areas over a wider range of brightness")
    ratio = common_ratio(nominal) if len(raws) == 1 else common_ratio(nominal, max_power=4)
    # the log-spline follows film curves but would also follow the log-periodic ripple one frame cannot
    # see: it is offered only to sweeps, whose exposure ratios are not all powers of one number
    candidates = [("polynomial", d) for d in range(1, config.max_degree + 1)]
    scored = None
    censored = None
    if len(raws) > 1 and ratio is None and config.max_knots >= 2:
        # windows are kept only when no reading is clipped, so a dark one survives when its noise
        # happened to lift it off 0: its value reads high (and its log is biased besides). A flexible
        # model would follow that bias, and held-out error would reward it, so equations whose darker
        # value is within ``dark_snr`` single-reading noise sd of 0 are left to no model here.
        reading_sd = np.sqrt(pairs.var_lo * config.window**2)
        clear = _subset(pairs, pairs.m_lo > config.dark_snr * reading_sd)
        if np.unique(clear.location).size >= config.min_locations:
            pairs = clear
            n_locations = int(np.unique(pairs.location).size)
            ends = (float(pairs.m_lo.min()), float(pairs.m_hi.max()))
            measured = ends
            # two sizes, not a choice of the knot count: held-out error, dominated by the numerous dark
            # equations, cannot see the shoulder, and with no knot beyond the data the fit is stable in
            # the count (docs/calibration.md). A power law (2 knots) for linear and gamma cameras.
            candidates += [("log-spline", k) for k in sorted({2, config.max_knots})]
            pairs = _undithered(pairs, sensor.range_dn)
            # which pixels reach white in the brighter frame pins the curve at white against the darker
            # readings (the scale), free of the texture selection of the windows kept near white
            censored = _censored_with_pilot(raws, times, sensor, pairs, nominal,
                                            np.log(spline_knots(*ends, config.max_knots)))
            # the rounding error of a window is the same at every location of that brightness, so
            # held-out locations share it: models are compared where it is small against the value
            far = pairs.m_lo * sensor.range_dn >= 0.5 / config.rounding_tolerance
            if np.unique(pairs.location[far]).size >= config.min_locations:
                scored = far
    exposures = nominal
    iterations = 8 if config.refine_ratios else 1
    for _ in range(iterations):
        scores = {}
        fits = {}
        fold_fits = {}
        for kind, size in candidates:
            if kind == "polynomial":
                if progress is not None:
                    progress(f"degree {size}/{config.max_degree} ({pairs.m_lo.size} equations)")
                coef = _solve(pairs, exposures, size)
                if not _monotone(coef, measured):
                    continue
                mean, se, held = _held_out(pairs, exposures, size, config.folds, scored)
                held = [Response(tuple(c)) for c in held]
            else:
                if progress is not None:
                    progress(f"log-spline, {size} knots ({pairs.m_lo.size} equations)")
                # the last knot at the top of the data: from there to white, where f(1) = 1 is set, the
                # curve is the power law of the last slope. The ratio equations barely see f(1) / f(top)
                # (the weakest direction of the fit by far), so a spline piece beyond the data, with its
                # curvature free, would set the scale of the whole curve from noise
                knots = tuple(spline_knots(*ends, size))
                knots_u = np.log(knots)
                coef = _solve_spline(pairs, exposures, knots_u, censored=censored)[0]
                if not _monotone_curve(Response(tuple(coef), knots=knots), measured):
                    continue
                mean, se, held = _held_out_curve(
                    pairs, exposures,
                    lambda sel, ku=knots_u: _solve_spline(pairs, exposures, ku, sel, censored=censored)[0],
                    lambda c, kn=knots: Response(tuple(c), knots=kn), config.folds, scored)
                held = [Response(tuple(c), knots=knots) for c in held]
                coef = (coef, knots)
            scores[kind, size] = (mean, se)
            fits[kind, size] = coef
            fold_fits[kind, size] = held
        if not scores:
            raise SveliveError("no polynomial degree gives a monotone response on this data; use a frame with "
                               "more smooth areas, or check the pattern and the black and white levels")
        best = min(scores, key=lambda key: scores[key][0])
        # the simplest model within one standard error of the best: fewest free parameters (a polynomial
        # of degree d has d, a log-spline with k knots k - 1), a polynomial before a spline of as many
        chosen = min((key for key in scores if scores[key][0] <= scores[best][0] + scores[best][1]),
                     key=lambda key: (key[1] - (key[0] == "log-spline"), key[0] == "log-spline"))
        if chosen[0] == "polynomial":
            coef, knots = fits[chosen], ()
        else:
            coef, knots = fits[chosen]
        curve = Response(tuple(float(c) for c in coef), knots=knots)
        if not config.refine_ratios:
            break
        new = _refine_exposures(pairs, exposures, curve)
        converged = np.max(np.abs(np.log(new / exposures))) < 1e-4
        exposures = new
        if converged:
            break
    grid = np.linspace(0.0, 1.0, 513)
    if chosen[0] == "polynomial":
        degree = chosen[1]
        A, y = _design(pairs, exposures, degree)
        sigma = _residual_sigma(pairs, exposures, coef)
        chi2 = float(np.mean(((A @ coef[1:] - y) / sigma) ** 2))
        profile = _curve_uncertainty(A / sigma[:, None], max(chi2, 1.0), grid)
        del A, y, sigma
    else:
        _, a, b = _solve_spline(pairs, exposures, np.log(knots), censored=censored)
        chi2 = float(np.mean((a @ coef[1:] - b) ** 2))
        profile = _spline_uncertainty(a, max(chi2, 1.0), np.log(knots), coef, grid)
        del a, b
    pinned = _pinned_range(pairs, profile, grid, config.max_uncertainty, config.coverage_bins,
                           config.coverage_count)
    if pinned[1] - pinned[0] < config.min_span:
        raise SveliveError(
            f"the frame pins the response down only on brightness {pinned[0]:.2f}..{pinned[1]:.2f} "
            f"(need a span of {config.min_span:.2f} with standard error under {config.max_uncertainty:.1%} and "
            "constant regions at every level): use a frame of a still scene with large smooth areas from dark "
            "to bright and little noise")
    inside = (grid >= pinned[0]) & (grid <= pinned[1])
    uncertainty = float(profile[inside].max())
    band_m = np.linspace(pinned[0], pinned[1], 33)
    band_se = np.maximum(np.interp(band_m, grid, profile), _jackknife_error(fold_fits[chosen], band_m))
    stats = {
        "measured_range": list(pinned),
        "data_range": list(measured),
        "uncertainty": {"brightness": grid[::16].tolist(), "standard_error": profile[::16].tolist()},
        "band": {"brightness": band_m.tolist(), "linear": curve(band_m).tolist(),
                 "standard_error": band_se.tolist()},
        "locations": n_locations,
        "equations": int(pairs.m_lo.size),
        "held_out_error": {_model_name(*key): {"mean": m, "standard_error": s} for key, (m, s) in scores.items()},
        "reduced_chi2": chi2,
        "curve_uncertainty": uncertainty,
        "exposures": exposures.tolist(),
        "nominal_exposures": nominal.tolist(),
        "pattern": str(pattern),
        "frames": len(raws),
        "exposure_times": times.tolist() if exposure_times is not None else None,
        # a sweep's near-coincidences (1.5 against 4 agree to 1e-3 at the 12th root) give ripples no
        # polynomial can follow: only common ratios within the fourth root of the smallest step count
        "common_ratio": ratio,
        # the sweep's pixels near white that pin the log-spline's scale (None: not used)
        "pixels_near_white": None if censored is None else {
            "pixels": int(censored.total.sum()), "at_white": int(censored.clipped.sum()),
            "width": [float(censored.width[censored.pair == q][0]) for q in np.unique(censored.pair)]},
    }
    return Response(curve.coefficients, (0.0, 1.0), float(sensor.black_level), float(sensor.white_level), stats,
                    knots)


def _model_name(kind: str, size: int) -> str:
    """Key of a candidate model in ``stats.held_out_error``: the degree ("3") or "log-spline 6" (knots)."""
    return str(size) if kind == "polynomial" else f"log-spline {size}"


def calibrate_frame(raw: np.ndarray | list[np.ndarray], pattern: Pattern | str, sensor: Sensor, *,
                    max_degree: int = 6, max_knots: int = SWEEP_KNOTS, points: int = 65, exposure_times=None,
                    progress: Callable[[str], None] | None = None) -> dict:
    """Response calibration of live raw frames, for the service: the response file's content
    plus ``curve``, ``points`` samples {"brightness": [...], "linear": [...]} of I = f(M) over
    [0, 1] for plotting (``stats.band`` has the uncertainty band over the measured range).
    ``raw`` is one frame, or a list of frames at ``exposure_times`` (a sweep). Raises
    SveliveError when the frames cannot calibrate (too few constant regions, too narrow a
    brightness range). ``max_knots``: see :class:`ResponseFitConfig`."""
    response = fit_response(raw, pattern, sensor, ResponseFitConfig(max_degree=max_degree, max_knots=max_knots),
                            exposure_times=exposure_times, progress=progress)
    m = np.linspace(0.0, 1.0, points)
    data = response.to_dict()
    data["curve"] = {"brightness": m.tolist(), "linear": np.clip(response(m), 0.0, 1.0).tolist()}
    return data


def write_json(data: dict, path: str | os.PathLike) -> Path:
    """Write ``data`` as indented JSON, atomically (svelive.core.atomic)."""
    return write_bytes_atomic(path, (json.dumps(data, indent=2) + "\n").encode())


def save_response(response: Response, path: str | os.PathLike) -> Path:
    """Write ``response`` as JSON, atomically."""
    return write_json(response.to_dict(), path)


def load_response(path: str | os.PathLike) -> Response:
    """Read a response written by :func:`save_response` (``svelive calibrate response``)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except OSError as exc:
        raise SveliveError(f"{path}: cannot read response file ({exc.strerror})") from None
    except json.JSONDecodeError as exc:
        raise SveliveError(f"{path}: not a response JSON file ({exc.msg} at line {exc.lineno})") from None
    if not isinstance(data, dict):
        raise SveliveError(f"{path}: a response file holds a JSON object")
    try:
        return Response.from_dict(data)
    except SveliveError as exc:
        raise SveliveError(f"{path}: {exc}") from None


# ----- known response curves, for simulating non-linear cameras -------------

@dataclass(frozen=True)
class ResponseCurve:
    """A known camera response: ``forward`` maps linear I in [0, 1] to brightness M in [0, 1],
    ``inverse`` maps back; both increasing with f(0) = 0, f(1) = 1."""

    name: str
    forward: Callable[[np.ndarray], np.ndarray]
    inverse: Callable[[np.ndarray], np.ndarray]


def _bisect_inverse(forward: Callable[[np.ndarray], np.ndarray]) -> Callable[[np.ndarray], np.ndarray]:
    grid = np.linspace(0.0, 1.0, 20001)
    values = forward(grid)
    return lambda m: np.interp(m, values, grid)


#: Inverse of the "polynomial" camera: I = 0.1 M + 0.3 M^2 + 0.6 M^3.
POLY3 = (0.0, 0.1, 0.3, 0.6)


def _s_curve(i: np.ndarray) -> np.ndarray:
    # film-like: flat toe and shoulder, steep middle; monotone since 0.6 < 1
    return i - 0.6 * np.sin(2 * np.pi * i) / (2 * np.pi)


CURVES: dict[str, ResponseCurve] = {
    "linear": ResponseCurve("linear", lambda i: np.asarray(i, np.float64), lambda m: np.asarray(m, np.float64)),
    "gamma2.2": ResponseCurve("gamma2.2", lambda i: np.power(np.clip(i, 0, 1), 1 / 2.2),
                              lambda m: np.power(np.clip(m, 0, 1), 2.2)),
    "poly3": ResponseCurve("poly3", _bisect_inverse(lambda m: P.polyval(m, POLY3)),
                           lambda m: P.polyval(np.asarray(m, np.float64), POLY3)),
    "s-curve": ResponseCurve("s-curve", _s_curve, _bisect_inverse(_s_curve)),
}


def simulate_nonlinear(radiance: np.ndarray, pattern: Pattern | str, sensor: Sensor, curve: ResponseCurve, *,
                       seed: int = 0) -> np.ndarray:
    """Raw SVE frame of a camera with response ``curve``, uint8/uint16 (H, W).

    The light is collected and made noisy linearly (the sensor's gain and read
    noise, :func:`svelive.simulate.simulate` at 16 bits of the same full well),
    then the response maps it to brightness and the ADC quantises to the
    sensor's bits.

    Args:
        radiance: float (H, W), radiance in DN (of ``sensor``) at exposure 1.
    """
    from svelive.simulate import simulate

    full_well = sensor.effective_gain * sensor.range_dn
    read_e = sensor.effective_read_noise * sensor.effective_gain
    fine = Sensor.from_full_well(16, full_well, read_e)
    scale = fine.range_dn / sensor.range_dn
    linear = simulate(np.asarray(radiance, np.float32) * scale, pattern, fine, seed=seed).raw
    m = curve.forward(np.clip(linear / fine.range_dn, 0.0, 1.0))
    dn = np.rint(float(sensor.black_level) + m * sensor.range_dn)
    dtype = np.uint8 if sensor.bits <= 8 else np.uint16
    return np.clip(dn, 0, sensor.white_level).astype(dtype)
