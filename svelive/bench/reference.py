"""The upper reference: sequential bracketing of a static scene.

The same exposures as the SVE tile, each captured as a full-resolution frame
with the same sensor, merged per pixel with inverse-variance weights of the
Poisson-Gaussian model. An SVE frame samples each exposure at 1/K of the
pixels, so this bounds what any SVE reconstruction can reach.
"""

from __future__ import annotations

import numpy as np

from svelive.core.pattern import Pattern
from svelive.core.sensor import Sensor
from svelive.simulation import simulate


def bracketing_merge(signals: list[np.ndarray], exposures: list[float], sensor: Sensor) -> np.ndarray:
    """Merge K full frames (signal above black, DN, float (H, W) each) into radiance, float32 (H, W).

    Uncensored readings only; weights e^2 / (e L0 / g + sigma^2) at the
    shot-noise maximum-likelihood radiance L0 = sum(s) / sum(e). Where all are
    censored, the lower bound the shortest exposure implies.
    """
    censor = sensor.censor_level
    gain, floor = sensor.effective_gain, sensor.floor_variance
    sum_s = np.zeros(signals[0].shape, np.float64)
    sum_e = np.zeros_like(sum_s)
    for s, e in zip(signals, exposures):
        valid = s < censor
        sum_s += np.where(valid, s, 0)
        sum_e += np.where(valid, e, 0)
    first = np.maximum(sum_s, 0) / np.maximum(sum_e, 1e-30)
    num = np.zeros_like(sum_s)
    den = np.zeros_like(sum_s)
    for s, e in zip(signals, exposures):
        w = np.where(s < censor, e * e / (e * first / gain + floor), 0)
        num += w * s / e
        den += w
    shortest = int(np.argmin(exposures))
    bound = signals[shortest] / exposures[shortest]
    image = np.where(den > 0, num / np.maximum(den, 1e-30), bound)
    return np.maximum(image, 0).astype(np.float32)


def bracketing_reference(radiance: np.ndarray, pattern: Pattern | str, sensor: Sensor, seed: int = 0) -> np.ndarray:
    """Simulate one full frame per exposure level of ``pattern`` and merge them, float32 (H, W) radiance."""
    pattern = Pattern.parse(pattern)
    exposures = [float(e) for e in pattern.levels]
    signals = []
    for k, e in enumerate(exposures):
        raw = simulate(radiance, Pattern.parse(f"{e:g}"), sensor, seed=seed * 1000 + k + 1).raw
        signals.append(raw.astype(np.float32) - np.float32(sensor.black_level))
    return bracketing_merge(signals, exposures, sensor)
