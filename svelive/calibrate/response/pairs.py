"""The fit's data from the frames (steps 1-3 of svelive.calibrate.response): per exposure level, a plane
fitted to its readings over each window, the frame's own noise curve and the chi-square test that keeps
locally constant windows, and the ratio equations between every two flat levels at a location
(:class:`_Pairs`) with their noise, the rounding a constant window shares included."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable

import cv2
import numpy as np

from svelive.calibrate.noise import noise_curve_frame
from svelive.calibrate.response.config import ResponseFitConfig
from svelive.core.errors import SveliveError
from svelive.core.pattern import Pattern
from svelive.core.sensor import Sensor
from svelive.noise.model import QUANTISATION_VARIANCE
from svelive.noise.stats import chi2_quantile


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
        limit = chi2_quantile(cfg.flat_quantile, dof) / dof
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


def _subset(pairs: _Pairs, sel) -> _Pairs:
    return _Pairs(*(getattr(pairs, f)[sel] for f in pairs.__dataclass_fields__))
