"""The noise model's value types: the estimator's knobs, an estimate and its uncertainty, samples, a fitted line.

The model is the sensor's (svelive/core/sensor.py): a reading with expected signal
``s`` DN above black has variance ``s / gain + read_noise^2 + 1/12`` DN^2 (the
1/12 is uniform quantisation). :func:`variance_uncertainty` and :func:`agree` read
estimates (how well one states the variance; whether two of one sensor agree).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from svelive.core.sensor import QUANTISATION_VARIANCE, Sensor


@dataclass(frozen=True)
class EstimatorConfig:
    """Knobs of the single-frame estimator (the defaults are the documented method).

    Attributes:
        max_samples: pixel pairs used at most (a strided subset of the frame beyond that).
        flat_quantile: a place is flat when its neighbour groups' spread is below this quantile
            of the spread pure noise gives,
        region_quantile: and the residuals of its 3x3-tile block below this quantile of theirs.
        bins: signal bins at most.
        min_bin: samples per bin at least.
        outlier_tolerance: a bin more than this fraction (plus 3 standard errors) above the line is dropped.
        iterations: passes of select-fit after the first, model-free one.
        reach: farthest neighbour, pixels (Chebyshev distance).
        max_ratio: a neighbour's exposure is at least 1 / max_ratio times the pixel's.
        clip_sigma: per-bin clipping of squared residuals, in standard deviations.
        temporal_clip_sigma: the same for temporal samples alone (static pixels' frame differences):
            they hold no texture, only the odd missed motion, and a 3-sigma clip with the Gaussian
            correction reads the variance up to 17 % low where shot noise of a few electrons has
            heavier tails than a Gaussian (a low read noise beside a small full well).
        start_fraction: the first pass keeps this flattest fraction of every signal bin.
        max_shot_ratio: if > 0, the model passes leave out samples whose shot variance exceeds this
            many times the read noise's (off: it costs the read noise of bright frames their leverage).
        block: side of the sample blocks in tiles (odd); the region test uses the other samples of a block.
        texture_uncertainty: add to the fit's covariance the shift a texture term would make
            (:func:`_with_texture_uncertainty`),
        strict_fraction: and the shift a stricter selection makes (flat quantile times this, region
            median; 0: off; :func:`_with_selection_uncertainty`).
        cancellation: estimate the gain with texture cancelled across exposures (:func:`cancellation_fit`)
            where the pattern allows it, and keep it where it is known to within ``cancel_max_sigma``
            (relative); else the residuals above.
        cancel_bins: signal bins per geometry there;
        cancel_fraction: the flattest fraction of every bin kept (by the other cells of the block),
        cancel_flat: and every cell whose block's other cells are as flat as noise (their standardised
            residuals below the ``region_quantile`` of the chi-square noise alone gives; False: the
            fraction alone, as before issue 12.1's fifth pass);
        cancel_level: a cell's level may differ from its block's by this many times the lowest
            exposure's noise variance;
        cancel_mismatch: the relative difference allowed between the texture two exposures see;
        cancel_max_samples: residuals read at most (a strided subset of the frame beyond that);
        cancel_iterations: passes of select-fit there after the first (under the sensor defaults);
        cancel_jackknife: horizontal bands of the frame left out one at a time to measure the joint
            fit's spread (:func:`_with_jackknife`; 0: its own covariance alone).
        cancel_symmetric: where the nearest ring has symmetric and one-sided geometries, the joint fit
            of the symmetric ones alone is taken where the one-sided ones bias it
            (:func:`_without_gradient_bias`; issue 12.1, sixth pass; False: all of them, as before);
        cancel_when_biased: take a joint fit less precise than ``cancel_max_sigma`` where the residual
            fit's slope lies beyond two of the joint fit's standard deviations above it, or where there
            is no residual fit (:func:`_preferred`).
    """

    max_samples: int = 40_000
    flat_quantile: float = 0.5
    region_quantile: float = 0.75
    bins: int = 24
    min_bin: int = 100
    outlier_tolerance: float = 0.1
    iterations: int = 2
    reach: int = 2
    max_ratio: float = 0.13
    clip_sigma: float = 3.0
    temporal_clip_sigma: float = 8.0
    start_fraction: float = 0.25
    max_shot_ratio: float = 0.0
    block: int = 3
    texture_uncertainty: bool = True
    strict_fraction: float = 0.5
    cancellation: bool = True
    cancel_bins: int = 16
    cancel_fraction: float = 0.25
    cancel_flat: bool = True
    cancel_level: float = 1.0
    cancel_mismatch: float = 0.1
    cancel_max_sigma: float = 0.5
    cancel_max_samples: int = 400_000
    cancel_iterations: int = 1
    cancel_jackknife: int = 16
    cancel_symmetric: bool = True
    cancel_when_biased: bool = True


@dataclass(frozen=True)
class NoiseEstimate:
    """A sensor noise model and how well it is known.

    Attributes:
        gain: electrons per DN.
        read_noise: read noise, DN (standard deviation, quantisation excluded).
        gain_sigma: standard uncertainty of ``gain`` (e-/DN); 0 when given; the prior's (``ln 4`` times the
            value) when the data did not tell it; None when unknown.
        read_noise_sigma: standard uncertainty of ``read_noise`` (DN), likewise.
        samples: noise samples (pixel pairs; residuals when the texture-cancelled fit was taken) the
            estimate rests on.
        source: "given" (both from the user or datasheet), "estimated" (from the data,
            a given value kept), "default" (the data could not tell; the sensor defaults).
    """

    gain: float
    read_noise: float
    gain_sigma: float | None
    read_noise_sigma: float | None
    samples: int
    source: str

    @staticmethod
    def given(sensor: Sensor) -> NoiseEstimate:
        """The model of a sensor that gives both its gain and its read noise (source "given", no uncertainty)."""
        return NoiseEstimate(sensor.gain, sensor.read_noise, 0.0, 0.0, 0, "given")

    def to_dict(self) -> dict:
        """JSON-safe description (for /api/state): floats or None."""
        def num(v: float | None) -> float | None:
            return None if v is None or not math.isfinite(v) else float(v)
        return {"gain": num(self.gain), "read_noise": num(self.read_noise), "gain_sigma": num(self.gain_sigma),
                "read_noise_sigma": num(self.read_noise_sigma), "samples": int(self.samples),
                "source": self.source}

    def attributes(self) -> dict[str, float | str]:
        """Flat EXR header attributes (floats and a string); unknown uncertainties are left out."""
        out: dict[str, float | str] = {"noiseGain": float(self.gain), "noiseReadNoise": float(self.read_noise),
                                       "noiseSource": self.source}
        if self.gain_sigma is not None and math.isfinite(self.gain_sigma):
            out["noiseGainSigma"] = float(self.gain_sigma)
        if self.read_noise_sigma is not None and math.isfinite(self.read_noise_sigma):
            out["noiseReadNoiseSigma"] = float(self.read_noise_sigma)
        return out

    def apply(self, sensor: Sensor) -> Sensor:
        """``sensor`` with this gain and read noise where it has none (given values are never overridden)."""
        return replace(sensor, gain=self.gain if sensor.gain is None else sensor.gain,
                       read_noise=self.read_noise if sensor.read_noise is None else sensor.read_noise)

    def describe(self) -> str:
        """One line for ``svelive reconstruct -v``."""
        def pm(v: float | None) -> str:
            return "" if v is None or not math.isfinite(v) or v == 0 else f" +- {v:.3g}"
        return (f"noise ({self.source}): gain {self.gain:.4g}{pm(self.gain_sigma)} e-/DN, read noise "
                f"{self.read_noise:.3g}{pm(self.read_noise_sigma)} DN, {self.samples} samples")


@dataclass(frozen=True)
class NoiseSamples:
    """Noise samples of one or more frames, each with a known expected value ``t / gain + R``.

    Attributes:
        t: float64 (N,), the shot-noise coordinate, DN (the signal, scaled by the residual's form).
        u: float64 (N,), the squared residual normalised so that E[u] = t / gain + R, DN^2.
    """

    t: np.ndarray
    u: np.ndarray

    @property
    def size(self) -> int:
        return int(self.t.size)

    @staticmethod
    def join(parts: list[NoiseSamples]) -> NoiseSamples:
        if not parts:
            return NoiseSamples(np.zeros(0), np.zeros(0))
        return NoiseSamples(np.concatenate([p.t for p in parts]), np.concatenate([p.u for p in parts]))


@dataclass(frozen=True)
class LineFit:
    """variance = slope * t + intercept, fitted over signal bins.

    Attributes:
        slope: 1 / gain, DN^2 per DN; intercept: R = read^2 + 1/12, DN^2; cov: 2x2 covariance of (slope, intercept).
        bins_t, bins_v, bins_n, inlier: the bins (signal, robust variance, count, kept by the fit).
    """

    slope: float
    intercept: float
    cov: np.ndarray
    bins_t: np.ndarray
    bins_v: np.ndarray
    bins_n: np.ndarray
    inlier: np.ndarray
    fixed_slope: bool = False
    texture: float = 0.0
    texture_sigma: float = 0.0

    def variance(self, t: np.ndarray | float) -> np.ndarray | float:
        return np.maximum(self.slope * np.asarray(t) + self.intercept, QUANTISATION_VARIANCE)


def variance_uncertainty(estimate: NoiseEstimate) -> float:
    """The largest relative standard uncertainty of the modelled variance ``v(t) = t / g + r^2 + 1/12`` over
    every signal ``t >= 0`` (DN), a float >= 0; ``inf`` when an uncertainty is unknown.

    With independent errors ``sd(v) = sqrt((t sd(g) / g^2)^2 + (2 r sd(r))^2)``, and since
    ``sqrt(a^2 + b^2) <= a + b``, ``sd(v) / v <= max(sd(g) / g, 2 r sd(r) / (r^2 + 1/12))``: the
    shot end's and the dark end's relative uncertainties, whichever is larger.
    """
    if estimate.gain_sigma is None or estimate.read_noise_sigma is None:
        return math.inf
    shot = estimate.gain_sigma / max(estimate.gain, 1e-12)
    dark = 2.0 * estimate.read_noise * estimate.read_noise_sigma / (estimate.read_noise**2 + QUANTISATION_VARIANCE)
    value = max(shot, dark)
    return value if math.isfinite(value) else math.inf


def agree(a: NoiseEstimate, b: NoiseEstimate, sigmas: float = 3.0) -> bool:
    """Whether two estimates of one sensor agree: gain and read noise each within ``sigmas`` combined
    standard uncertainties (an unknown uncertainty agrees with anything)."""
    for x, y, sx, sy in ((a.gain, b.gain, a.gain_sigma, b.gain_sigma),
                         (a.read_noise, b.read_noise, a.read_noise_sigma, b.read_noise_sigma)):
        if sx is None or sy is None:
            continue
        if abs(x - y) > sigmas * math.hypot(sx, sy):
            return False
    return True
