"""Stability sweeps: controlled synthetic scenes with one difficulty axis each, run for every method.

Each sweep returns a :class:`Sweep` (difficulty values and, per method, the
error at each). Frames are small (96x96 by default) and seeds fixed, so the
whole suite runs in seconds and the tests in tests/test_stability.py can use it.

Error measures (lower is better):
- ``mean |log2 error|``: mean absolute error in stops against what the frame
  can tell, min(truth, full scale of the shortest exposure): above that the
  frame only says "at least", and a method cannot do better than the bound.
- ``relative RMS error``: RMS(out - truth) / mean(truth).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Callable

import numpy as np

from svelive.bench.runner import Setting
from svelive.bench.scenes import BENCH_SENSOR
from svelive.reconstruction.methods import METHODS
from svelive.pattern import Pattern
from svelive.reconstruction.input import prepare
from svelive.sensor import Sensor
from svelive.simulate import simulate

SIZE = 96
PATTERN = "1,4/16,64"
SEED = 11


@dataclass
class Sweep:
    """One sweep's curves."""

    name: str
    title: str
    axis: str
    error: str
    difficulty: list[float]
    errors: dict[str, list[float]] = field(default_factory=dict)
    log_y: bool = True
    notes: str = ""


def stability_settings() -> list[Setting]:
    """Every registered method with default options, and the OpenCV baseline."""
    return [Setting(name, name) for name in METHODS] + [Setting("baseline", "baseline")]


def reconstruct_with(setting: Setting, raw: np.ndarray, pattern: Pattern | str, sensor: Sensor = BENCH_SENSOR) -> np.ndarray:
    """Reconstruct ``raw`` with a setting, float32 (H, W)."""
    return setting.run(prepare(raw, pattern, sensor)).image


def measurable(truth: np.ndarray, pattern: Pattern | str, sensor: Sensor = BENCH_SENSOR) -> np.ndarray:
    """What a frame can tell: truth capped at the radiance where the shortest exposure saturates."""
    return np.minimum(truth, sensor.censor_level / float(Pattern.parse(pattern).levels[0]))


def stops_error(out: np.ndarray, target: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean |log2(out / target)| (stops), values floored at 1e-3 DN; over ``mask`` if given."""
    err = np.abs(np.log2(np.maximum(out, 1e-3) / np.maximum(target, 1e-3)))
    return float(err[mask].mean() if mask is not None else err.mean())


def relative_rms(out: np.ndarray, truth: np.ndarray) -> float:
    """RMS(out - truth) / mean(truth)."""
    return float(np.sqrt(np.mean((out.astype(np.float64) - truth) ** 2)) / max(float(truth.mean()), 1e-12))


def slanted(size: int = SIZE, angle_deg: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
    """Coordinates (u across, v along) of a grid rotated by ``angle_deg``, float64 (size, size) each, centred."""
    y, x = np.mgrid[0:size, 0:size].astype(np.float64) - (size - 1) / 2
    a = np.deg2rad(angle_deg)
    return x * np.cos(a) + y * np.sin(a), -x * np.sin(a) + y * np.cos(a)


def _run_sweep(sweep: Sweep, scenes: Callable[[float], tuple[np.ndarray, np.ndarray, str, str]],
               measure: Callable[[np.ndarray, np.ndarray, str], float], settings: list[Setting],
               sensor: Sensor = BENCH_SENSOR) -> Sweep:
    """``scenes(d)`` gives (raw, truth, pattern used to simulate, pattern given to the methods)."""
    for setting in settings:
        sweep.errors[setting.label] = []
    for d in sweep.difficulty:
        raw, truth, _, nominal = scenes(d)
        for setting in settings:
            out = reconstruct_with(setting, raw, nominal, sensor)
            sweep.errors[setting.label].append(measure(out, truth, nominal))
    return sweep


def _simulated(truth: np.ndarray, pattern: str, seed: int = SEED) -> np.ndarray:
    return simulate(truth, pattern, BENCH_SENSOR, seed=seed).raw


def edge_across_saturation(settings: list[Setting], pattern: str = PATTERN) -> Sweep:
    """A slanted step edge whose bright side climbs through the saturation of every exposure but the shortest."""
    sweep = Sweep("edge", "edge across saturation", "edge contrast (stops)", "mean |log2 error| near the edge",
                  [float(c) for c in np.arange(0.0, 10.01, 0.5)])
    u, _ = slanted()
    dark = 0.25 * BENCH_SENSOR.range_dn / float(Pattern.parse(pattern).levels[-1])
    band = np.abs(u) <= 3

    def scene(c: float):
        truth = np.where(u > 0, dark * 2.0**c, dark).astype(np.float32)
        return _simulated(truth, pattern), truth, pattern, pattern

    return _run_sweep(sweep, scene, lambda out, truth, p: stops_error(out, measurable(truth, p), band), settings)


def texture_frequency(settings: list[Setting], pattern: str = PATTERN) -> Sweep:
    """A slanted sinusoidal grating (contrast 1:3) from coarse to the sensor's Nyquist frequency."""
    sweep = Sweep("texture", "texture frequency (aliasing, moire)", "frequency (cycles / pixel, Nyquist 0.5)",
                  "relative RMS error", [float(f) for f in np.linspace(0.02, 0.5, 13)])
    u, _ = slanted(angle_deg=7.0)
    mean = 0.5 * BENCH_SENSOR.range_dn / float(Pattern.parse(pattern).levels[-1])

    def scene(f: float):
        truth = (mean * (1.0 + 0.5 * np.sin(2 * np.pi * f * u))).astype(np.float32)
        return _simulated(truth, pattern), truth, pattern, pattern

    return _run_sweep(sweep, scene, lambda out, truth, p: relative_rms(out, truth), settings)


def low_light(settings: list[Setting], pattern: str = PATTERN) -> Sweep:
    """A flat scene from half the longest exposure's full scale down by up to 14 stops (photon count, read noise)."""
    sweep = Sweep("low_light", "low light (photon count, read noise)", "stops below half fill of the longest exposure",
                  "relative RMS error", [float(s) for s in range(0, 15)])
    top = 0.5 * BENCH_SENSOR.range_dn / float(Pattern.parse(pattern).levels[-1])

    def scene(s: float):
        truth = np.full((SIZE, SIZE), top * 2.0**-s, np.float32)
        return _simulated(truth, pattern), truth, pattern, pattern

    return _run_sweep(sweep, scene, lambda out, truth, p: relative_rms(out, truth), settings)


def saturated_fraction(settings: list[Setting], pattern: str = PATTERN) -> Sweep:
    """A log ramp across the frame shifted so that a growing fraction of it saturates even the shortest exposure."""
    sweep = Sweep("saturation", "saturated fraction", "fraction of pixels beyond the shortest exposure",
                  "mean |log2 error| vs what the frame can tell", [float(f) for f in np.linspace(0, 1, 11)])
    levels = Pattern.parse(pattern).levels
    limit = BENCH_SENSOR.range_dn / float(levels[0])
    x = np.linspace(0, 1, SIZE)[None, :].repeat(SIZE, 0)
    span = 8.0  # stops across the frame

    def scene(f: float):
        truth = (limit * 2.0 ** (span * (x - (1.0 - f)))).astype(np.float32)  # column 1 - f sits at the limit
        return _simulated(truth, pattern), truth, pattern, pattern

    return _run_sweep(sweep, scene, lambda out, truth, p: stops_error(out, measurable(truth, p)), settings)


def _textured_scene(pattern: str) -> np.ndarray:
    """Smooth texture over ~6 stops that every exposure of ``pattern`` measures somewhere, float32 (SIZE, SIZE)."""
    u, v = slanted(angle_deg=11.0)
    levels = Pattern.parse(pattern).levels
    top = 0.5 * BENCH_SENSOR.range_dn / float(levels[0])
    return (top * 2.0 ** (-6.0 * (0.5 + 0.25 * np.sin(u / 9.0) + 0.25 * np.cos(v / 13.0)))).astype(np.float32)


def hot_dead_pixels(settings: list[Setting], pattern: str = PATTERN) -> Sweep:
    """Half hot (stuck at white) and half dead (stuck at black) pixels, up to 2% of the frame."""
    sweep = Sweep("defects", "hot and dead pixels", "fraction of defective pixels", "mean |log2 error|",
                  [float(f) for f in np.linspace(0, 0.02, 9)])
    truth = _textured_scene(pattern)
    clean = _simulated(truth, pattern)
    order = np.random.default_rng(SEED).permutation(truth.size)

    def scene(f: float):
        raw = clean.copy().ravel()
        n = int(round(f * raw.size))
        raw[order[: n // 2]] = int(BENCH_SENSOR.white_level)
        raw[order[n // 2: n]] = 0
        return raw.reshape(clean.shape), truth, pattern, pattern

    return _run_sweep(sweep, scene, lambda out, t, p: stops_error(out, measurable(t, p)), settings)


def phase_error(settings: list[Setting], pattern: str = PATTERN) -> Sweep:
    """The methods told a tile whose origin is off by 0 or 1 pixel in x, y or both."""
    sweep = Sweep("phase", "pattern phase off by one pixel", "offset: 0 none, 1 x, 2 y, 3 x and y",
                  "mean |log2 error|", [0.0, 1.0, 2.0, 3.0])
    truth = _textured_scene(pattern)
    raw = _simulated(truth, pattern)
    tile = Pattern.parse(pattern).tile

    def scene(code: float):
        shift = (int(code) // 2, int(code) % 2)
        told = Pattern(np.roll(tile, shift, axis=(0, 1)))
        return raw, truth, pattern, str(told)

    return _run_sweep(sweep, scene, lambda out, t, p: stops_error(out, measurable(t, pattern)), settings)


def exposure_ratio_error(settings: list[Setting], pattern: str = PATTERN) -> Sweep:
    """The true exposures other than the shortest are off by -10% .. +10% from the nominal tile the methods use."""
    sweep = Sweep("ratio", "exposure ratios wrong", "error of the true exposure ratios (%)", "mean |log2 error|",
                  [float(p) for p in np.arange(-10.0, 10.01, 2.5)])
    truth = _textured_scene(pattern)
    tile = Pattern.parse(pattern).tile

    def scene(percent: float):
        true_tile = np.where(tile > tile.min(), tile * (1 + percent / 100.0), tile)
        raw = _simulated(truth, str(Pattern(true_tile)))
        return raw, truth, str(Pattern(true_tile)), pattern

    return _run_sweep(sweep, scene, lambda out, t, p: stops_error(out, measurable(t, pattern)), settings)


SWEEPS: dict[str, Callable[[list[Setting]], Sweep]] = {
    "edge": edge_across_saturation,
    "texture": texture_frequency,
    "low_light": low_light,
    "saturation": saturated_fraction,
    "defects": hot_dead_pixels,
    "phase": phase_error,
    "ratio": exposure_ratio_error,
}


def run_stability(settings: list[Setting] | None = None) -> list[dict[str, object]]:
    """Every sweep for every setting, JSON-ready."""
    settings = stability_settings() if settings is None else settings
    return [asdict(make(settings)) for make in SWEEPS.values()]
