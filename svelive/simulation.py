"""Render raw SVE frames from linear HDR images with a physical sensor model.

The model is the one of the method notes: a pixel of relative exposure e seeing
radiance L (DN at exposure 1) collects Poisson(g e L) electrons, g electrons per
DN; Gaussian read noise is added, then the black level, rounding to an integer
and clipping to [0, white]. The ground truth is L itself, in the project's
output unit, so it compares directly with any reconstruction.

Colour: with a colour filter layout (svelive.core.cfa), the radiance is linear camera
RGB (H, W, 3) and each pixel sees its own channel of it through its exposure,
with the same noise model; the ground truth is then the RGB radiance.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from svelive.core.cfa import ColourFilter
from svelive.core.errors import SveliveError
from svelive.core.pattern import Pattern
from svelive.core.sensor import Sensor
from svelive.exr import read_exr, read_luminance

#: Shipped sample scenes (256x256 crops of the OpenEXR sample images, BSD licence).
SAMPLE_SCENES = ("desk", "mttamwest", "cannon")


@dataclass(frozen=True)
class SimulatedFrame:
    """A simulated raw frame and what it should reconstruct to.

    Attributes:
        raw: uint8 (bits <= 8) or uint16 (H, W), DN including the black level.
        truth: float32 (H, W), radiance in DN at relative exposure 1; (H, W, 3) linear
            camera RGB, DN at relative exposure 1 per channel, for a colour frame.
    """

    raw: np.ndarray
    truth: np.ndarray


def sample_scene_path(name: str) -> Path:
    """Path of a shipped sample scene (one of SAMPLE_SCENES)."""
    if name not in SAMPLE_SCENES:
        raise SveliveError(f"unknown sample scene {name!r}; choose from {', '.join(SAMPLE_SCENES)}")
    return Path(str(resources.files("svelive") / "data" / f"{name}.exr"))


def load_sample_scene(name: str, rgb: bool = False) -> np.ndarray:
    """A shipped sample scene, relative linear units: luminance float32 (256, 256), or with
    ``rgb`` its linear RGB, float32 (256, 256, 3)."""
    path = sample_scene_path(name)
    if not rgb:
        return read_luminance(path)
    channels, _ = read_exr(path)
    return np.ascontiguousarray(np.stack([channels[c] for c in "RGB"], axis=-1), dtype=np.float32)


def exposure_scale(radiance: np.ndarray, pattern: Pattern, sensor: Sensor, *,
                   stops_below_fill: float = 0.0, percentile: float = 99.9) -> float:
    """Factor that maps relative ``radiance`` (H, W) or RGB (H, W, 3) to DN at exposure 1.

    At ``stops_below_fill = 0`` the scene's brightest point (its ``percentile``
    of luminance, robust to a few hot pixels; of the brightest channel of each
    pixel for RGB) just fills the lowest exposure; every stop more makes the
    scene twice as dim (a noise-limited scene at 5).
    """
    radiance = np.asarray(radiance)
    if radiance.ndim == 3:
        radiance = radiance.max(axis=2)
    peak = float(np.percentile(radiance, percentile))
    if not peak > 0:
        raise SveliveError("the scene has no positive radiance to scale")
    return sensor.range_dn / (peak * float(pattern.levels[0])) * 2.0 ** (-stops_below_fill)


def simulate(radiance: np.ndarray, pattern: Pattern | str, sensor: Sensor, *,
             cfa: ColourFilter | str | None = None, seed: int | np.random.Generator = 0) -> SimulatedFrame:
    """Render one raw SVE frame.

    Args:
        radiance: float (H, W), scene radiance in DN at relative exposure 1 (see
            :func:`exposure_scale`), or with ``cfa`` linear camera RGB (H, W, 3) in
            that unit per channel; negative values are treated as 0.
        pattern: exposure pattern (or its text form).
        sensor: bit depth, black/white level, gain and read noise (unknown gain and
            read noise take the sensor's defaults).
        cfa: the colour filter layout (or its text form, e.g. ``"RGGB"``): each pixel
            sees its channel of the RGB radiance. None for a monochrome sensor.
        seed: seed or generator for the noise; equal seeds give equal frames.
    """
    pattern = Pattern.parse(pattern)
    radiance = np.asarray(radiance, dtype=np.float32)
    if cfa is None and radiance.ndim == 3:
        raise SveliveError(f"radiance has shape {radiance.shape}: an RGB image needs the colour filter "
                           "(cfa='RGGB', --cfa), or give a 2-D luminance image")
    if cfa is not None and radiance.shape[2:] != (3,):
        raise SveliveError(f"with a colour filter the radiance must be RGB (H, W, 3), got shape {radiance.shape} "
                           "(give an RGB image, or no colour filter for a monochrome sensor)")
    if radiance.ndim != (2 if cfa is None else 3):
        raise SveliveError(f"radiance must be a 2-D luminance image, got shape {radiance.shape}")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    truth = np.clip(np.nan_to_num(radiance, nan=0.0, posinf=0.0), 0, None)
    seen = truth
    if cfa is not None:  # each pixel's own channel
        channels = ColourFilter.parse(cfa).channel_map(truth.shape[:2])
        seen = np.take_along_axis(truth, channels[..., None].astype(np.intp), axis=2)[..., 0]
    return SimulatedFrame(raw=_render(seen, pattern.exposure_map(seen.shape), sensor, rng), truth=truth)


def _render(radiance: np.ndarray, exposure: np.ndarray, sensor: Sensor, rng: np.random.Generator) -> np.ndarray:
    """Raw DN (uint8 or uint16 (H, W)) of pixels seeing ``radiance`` (float32 (H, W), >= 0) through ``exposure``."""
    gain = sensor.effective_gain
    # Cap the mean so that Poisson stays in range; anything that large saturates anyway.
    mean_electrons = np.minimum(radiance * exposure * gain, 1e12)
    electrons = rng.poisson(mean_electrons).astype(np.float64)
    dn = electrons / gain + rng.normal(0.0, sensor.effective_read_noise, radiance.shape) + sensor.black_level
    dtype = np.uint8 if sensor.bits <= 8 else np.uint16
    return np.clip(np.rint(dn), 0, sensor.white_level).astype(dtype)
