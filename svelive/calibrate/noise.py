"""The sensor's noise model from calibration data: gain (electrons per DN) and read noise (DN).

The model is Poisson-Gaussian: a raw reading with expected signal ``s`` DN above
black has variance ``a s + b`` DN^2, with ``a = 1 / gain`` and
``b = read_noise^2 + 1/12`` (the 1/12 is uniform quantisation). The variance is
measured against the signal in bins and the line is fitted by weighted least
squares, from either

- a pair of frames of the same static scene or flat field (the pixel-wise
  difference removes the scene, whatever its texture, vignetting or mask), or
- one frame: the SVE estimator of :mod:`svelive.noise` (each pixel against its
  more exposed neighbours at places its neighbours show flat).

:func:`noise_curve_frame` (the older single-frame curve, second differences of
one exposure's sub-image) stays for the response calibration's local-flatness
test; it reads 10-40x too high on textured scenes, so the noise estimate no
longer uses it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from svelive.core.camera import Camera
from svelive.core.errors import SveliveError
from svelive.core.pattern import Pattern
from svelive.core.sensor import Sensor
from svelive.noise import (
    PRIOR_LOG_SIGMA,
    QUANTISATION_VARIANCE,
    EstimatorConfig,
    LineFit,
    chi2_quantile,
    frame_fit,
    pair_fit,
)


@dataclass(frozen=True)
class NoiseCurve:
    """Measured noise variance against signal, one entry per signal bin.

    Attributes:
        signal: float64 (B,), mean signal above black of the bin, DN.
        variance: float64 (B,), noise variance of one reading there, DN^2.
        count: int64 (B,), number of samples in the bin.
    """

    signal: np.ndarray
    variance: np.ndarray
    count: np.ndarray

    def at(self, signal: np.ndarray | float) -> np.ndarray:
        """Variance (DN^2) at ``signal`` (DN), linearly interpolated between bins, float64."""
        return np.interp(signal, self.signal, self.variance)


@dataclass(frozen=True)
class NoiseModel:
    """Fitted Poisson-Gaussian noise model.

    Attributes:
        gain: electrons per DN (1 / slope).
        read_noise: read noise, DN (standard deviation, quantisation excluded).
        slope: a in variance = a * signal + b, DN^2 per DN.
        intercept: b, DN^2.
        signal_range: (low, high) signal above black covered by the data, DN.
        samples: number of pixel samples used.
        method: "pair" or "single-frame".
        residual_rms: rms relative deviation of the bins from the fitted line.
        gain_sigma, read_noise_sigma: standard uncertainties from the fit's covariance (None when
            not known); a read noise of 0 with a large sigma means the data had no dark enough pixels.
    """

    gain: float
    read_noise: float
    slope: float
    intercept: float
    signal_range: tuple[float, float]
    samples: int
    method: str
    residual_rms: float
    gain_sigma: float | None = None
    read_noise_sigma: float | None = None

    def to_dict(self) -> dict:
        return {"gain": self.gain, "read_noise": self.read_noise, "slope": self.slope,
                "intercept": self.intercept, "signal_range": list(self.signal_range),
                "samples": self.samples, "method": self.method, "residual_rms": self.residual_rms,
                "gain_sigma": self.gain_sigma, "read_noise_sigma": self.read_noise_sigma}

    def sensor(self, base: Sensor) -> Sensor:
        """``base`` with this gain and read noise."""
        return Sensor(base.bits, base.black_level, base.white_level, self.gain, self.read_noise)


def _check_frame(raw: np.ndarray, name: str) -> np.ndarray:
    raw = np.asarray(raw)
    if raw.ndim != 2 or raw.size == 0:
        raise SveliveError(f"{name} must be a non-empty single-channel 2-D array, got shape {raw.shape}")
    if raw.dtype.kind not in "uif":
        raise SveliveError(f"{name} has unsupported dtype {raw.dtype}")
    return raw.astype(np.float64)


def _bin_statistics(signal: np.ndarray, values: np.ndarray, statistic, bins: int,
                    min_count: int) -> NoiseCurve:
    """Bins of equal sample count over ``signal``; ``statistic(values_in_bin)`` gives the variance."""
    order = np.argsort(signal, kind="stable")
    n = order.size
    nbins = max(1, min(bins, n // min_count))
    edges = np.linspace(0, n, nbins + 1).astype(np.int64)
    s, v, c = [], [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        idx = order[lo:hi]
        if idx.size < min_count:
            continue
        s.append(float(np.mean(signal[idx])))
        v.append(float(statistic(values[idx])))
        c.append(idx.size)
    return NoiseCurve(np.array(s), np.array(v), np.array(c, dtype=np.int64))


def noise_curve_pair(raw1: np.ndarray, raw2: np.ndarray, sensor: Sensor, *, bins: int = 32,
                     min_count: int = 200) -> NoiseCurve:
    """Noise variance against signal from two frames of the same static scene.

    Args:
        raw1, raw2: (H, W) raw frames, DN including black, same shape.
        sensor: black and white level (a given gain or read noise is held fixed).
    A global brightness change between the frames (flicker) is removed first. Pixels are kept or
    dropped by the pair's mean signal, four noise standard deviations clear of raw 0 and of white
    (:func:`svelive.noise.pair_fit`), never by either reading: dropping the readings that hit 0
    truncated the noise of dark pixels and gave 0.0-0.98 DN read noise for a truth of 1.23 DN with a
    black level of 0. Bins are spaced in log signal (equal-count bins put nearly all of them at the
    dark end of a dim scene) and their variance is a clipped mean robust to a little motion.
    """
    return _curve(_pair(raw1, raw2, sensor, bins, min_count)[1])


def _pair(raw1: np.ndarray, raw2: np.ndarray, sensor: Sensor, bins: int = 32, min_count: int = 200,
          period: tuple[int, int] | None = None):
    a = _check_frame(raw1, "first frame")
    b = _check_frame(raw2, "second frame")
    if a.shape != b.shape:
        raise SveliveError(f"the two frames differ in size: {a.shape[1]}x{a.shape[0]} and {b.shape[1]}x{b.shape[0]}")
    black, white = float(sensor.black_level), float(sensor.white_level)
    usable = int(np.count_nonzero((a < white) & (b < white) & (a > 0) & (b > 0)))
    if usable < min_count:
        raise SveliveError(f"only {usable} pixels are neither saturated nor black in both frames; "
                           "use frames exposed well below saturation")
    config = EstimatorConfig(bins=bins, min_bin=min_count)
    samples, fit = pair_fit(a - black, b - black, sensor, config=config, period=period)
    if fit is None:
        raise SveliveError("the pair gives too few signal levels clear of black and white for a noise fit; "
                           "use frames with a range of brightness well below saturation")
    return samples, fit


def _curve(fit: LineFit) -> NoiseCurve:
    keep = fit.inlier
    return NoiseCurve(fit.bins_t[keep], fit.bins_v[keep], fit.bins_n[keep])


def _model(fit: LineFit, samples: int, method: str) -> NoiseModel:
    """The NoiseModel of a fitted line."""
    keep = fit.inlier
    v, model_v = fit.bins_v[keep], fit.variance(fit.bins_t[keep])
    resid = float(np.sqrt(np.mean(((v - model_v) / model_v) ** 2))) if keep.any() else float("nan")
    gain = 1.0 / fit.slope
    read = math.sqrt(max(fit.intercept - QUANTISATION_VARIANCE, 0.0))
    sd_r = math.sqrt(max(fit.cov[1, 1], 0.0))
    read_sigma = sd_r / (2 * read) if read > math.sqrt(sd_r) else math.sqrt(sd_r)
    return NoiseModel(gain=1.0 / fit.slope, read_noise=math.sqrt(max(fit.intercept - QUANTISATION_VARIANCE, 0.0)),
                      slope=fit.slope, intercept=fit.intercept,
                      signal_range=(float(fit.bins_t[keep].min()), float(fit.bins_t[keep].max())),
                      samples=samples, method=method, residual_rms=resid,
                      gain_sigma=(PRIOR_LOG_SIGMA * gain if fit.fixed_slope  # the default gain, not a measurement
                                  else math.sqrt(max(fit.cov[0, 0], 0.0)) * gain * gain),
                      read_noise_sigma=read_sigma)


def noise_curve_frame(raw: np.ndarray, pattern: Pattern | str, sensor: Sensor, *, bins: int = 24,
                      window: int = 3, quantile: float = 0.1, min_count: int = 50) -> NoiseCurve:
    """Noise variance against signal from one frame of a static scene.

    Every sub-image of one tile position (one exposure) is cut into 2x2 blocks;
    the block's second difference ``(x00 - x01 - x10 + x11) / 2`` cancels any
    locally bilinear scene and has the variance of one reading where the scene
    is smooth. Over ``window`` x ``window`` blocks the mean square of these
    differences is sigma^2 chi^2_n / n (n = window^2) on smooth areas and larger
    on textured ones, so per signal bin the ``quantile`` of the window values,
    divided by the same quantile of chi^2_n / n, estimates sigma^2 as long as that
    fraction of the bin's windows is smooth. Windows with a clipped reading are
    left out.

    Args:
        raw: (H, W) raw frame, DN including black.
        pattern: exposure pattern (its tile says which pixels share an exposure).
        sensor: black and white level.
    """
    x = _check_frame(raw, "raw frame")
    pattern = Pattern.parse(pattern)
    th, tw = pattern.shape
    black, white = float(sensor.black_level), float(sensor.white_level)
    span = 2 * window
    signals, energies = [], []
    for a in range(th):
        for b in range(tw):
            sub = x[a::th, b::tw]
            ny, nx = sub.shape[0] // span, sub.shape[1] // span
            if ny < 1 or nx < 1:
                continue
            cells = sub[:ny * span, :nx * span].reshape(ny, window, 2, nx, window, 2)
            d = 0.5 * (cells[:, :, 0, :, :, 0] - cells[:, :, 0, :, :, 1]
                       - cells[:, :, 1, :, :, 0] + cells[:, :, 1, :, :, 1])
            clipped = ((cells >= white) | (cells <= 0)).any(axis=(1, 2, 4, 5))
            keep = ~clipped
            energies.append((d * d).mean(axis=(1, 3))[keep])
            signals.append(cells.mean(axis=(1, 2, 4, 5))[keep] - black)
    if not signals:
        raise SveliveError(f"frame {x.shape[1]}x{x.shape[0]} is too small for noise estimation with a "
                           f"{tw}x{th} tile (need {span} tiles each way)")
    s = np.concatenate(signals)
    e = np.concatenate(energies)
    if s.size < 3 * min_count:
        raise SveliveError(f"only {s.size} unclipped {span}x{span}-tile windows; use a larger frame exposed "
                           "below saturation")
    dof = window * window
    correction = chi2_quantile(quantile, dof) / dof
    return _bin_statistics(s, e, lambda v: np.quantile(v, quantile) / correction, bins, min_count)


def fit_noise_model(curve: NoiseCurve, method: str, *, robust: bool = False,
                    outlier_factor: float = 1.3) -> NoiseModel:
    """Fit variance = a * signal + b to a noise curve by weighted least squares.

    The weights are the inverse standard deviation of each bin's variance estimate,
    ``sqrt((n - 1) / 2) / variance``, iterated with the fitted variance. With
    ``robust``, bins above ``outlier_factor`` times the line are dropped (texture
    only ever inflates a single-frame estimate).
    """
    s, v, n = curve.signal, curve.variance, curve.count.astype(np.float64)
    if s.size < 3:
        raise SveliveError(f"only {s.size} signal bins have enough samples; use larger frames or more area below saturation")
    lo, hi = float(s.min()), float(s.max())
    if not hi - lo >= 0.5 * hi:
        raise SveliveError(f"the data covers signals only from {lo:.1f} to {hi:.1f} DN; the slope needs a wider "
                           "range: use flats at several brightness levels or a scene with dark and bright areas")
    model_v = np.maximum(v, QUANTISATION_VARIANCE)
    A = np.stack([s, np.ones_like(s)], axis=1)
    inlier = np.ones(s.size, bool)
    for _ in range(6):
        # Bins short of smooth areas read high, never low: drop those well above the line and refit.
        w = np.sqrt(np.maximum(n - 1, 1) / 2.0) / np.maximum(model_v, QUANTISATION_VARIANCE) * inlier
        coef, *_ = np.linalg.lstsq(A * w[:, None], v * w, rcond=None)
        model_v = np.maximum(A @ coef, QUANTISATION_VARIANCE)
        if robust:
            inlier = v <= outlier_factor * model_v
    slope, intercept = float(coef[0]), float(coef[1])
    if not slope > 0:
        raise SveliveError("the noise does not grow with the signal in this data (slope <= 0); use frames with "
                           "a wide range of brightness and no motion between them")
    resid = float(np.sqrt(np.mean(((v - model_v) / model_v)[inlier] ** 2)))
    read_var = intercept - QUANTISATION_VARIANCE
    return NoiseModel(gain=1.0 / slope, read_noise=math.sqrt(max(read_var, 0.0)), slope=slope,
                      intercept=intercept, signal_range=(lo, hi), samples=int(n.sum()), method=method,
                      residual_rms=resid)


def calibrate_noise(frames: list[np.ndarray], sensor: Sensor, pattern: Pattern | str | None = None) -> NoiseModel:
    """Gain and read noise from two frames of a static scene, or from one frame (needs ``pattern``).

    Args:
        frames: one or two (H, W) raw frames, DN including black.
        sensor: black and white level.
        pattern: the exposure pattern, required for a single frame; for a pair it says which
            neighbours share a pixel's exposure (the pair is grouped by them).
    A single frame uses the SVE estimator of :mod:`svelive.noise` (residuals of each pixel against
    its more exposed neighbours at flat places); a pair, the difference of the frames.
    """
    if len(frames) == 2:
        samples, fit = _pair(frames[0], frames[1], sensor,
                             period=None if pattern is None else Pattern.parse(pattern).shape)
        return _model(fit, samples.size, "pair")
    if len(frames) == 1:
        if pattern is None:
            raise SveliveError("noise from a single frame needs the exposure pattern (--pattern)")
        raw = np.asarray(frames[0])
        camera = Camera(Pattern.parse(pattern), None, replace(sensor, gain=None, read_noise=None))
        fit, count = frame_fit(raw, camera)  # what svelive.reconstruct estimates, texture cancelled
        if fit is None:
            raise SveliveError("this frame has too few flat, unclipped places for a noise estimate; use a pair "
                               "of frames of a still scene, or a frame with smooth areas at several brightnesses")
        return _model(fit, count, "single-frame")
    raise SveliveError(f"noise estimation takes one frame of a static scene or a pair of frames, got {len(frames)}")
