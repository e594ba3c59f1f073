"""Benchmark scenes: real HDR images, scaled to a sensor and rendered as raw SVE frames."""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from svelive.core.errors import SveliveError
from svelive.core.pattern import Pattern
from svelive.core.sensor import Sensor
from svelive.exr import read_luminance
from svelive.simulation import exposure_scale

#: The benchmark sensor: 12 bits, 10 000 e- full well, 3 e- read noise (machine-vision CMOS).
BENCH_SENSOR = Sensor.from_full_well(12, 10_000, 3)

#: Noise levels: stops by which the scene's 99.9th percentile lies below the lowest exposure's full scale.
NOISE_LEVELS: dict[str, float] = {"bright": 0.0, "dim": 5.0}

#: The patterns of the issue: both 2x2 tiles and the line-interleaved (dual-gain) pattern.
PATTERNS: tuple[str, ...] = ("1,4/16,64", "1,2/4,8", "1/1/8/8")


def default_data_dir() -> Path:
    """``../shared/data/hdr`` beside the repository checkout (development machines only)."""
    return Path(__file__).resolve().parents[3] / "shared" / "data" / "hdr"


def shipped_data_dir() -> Path:
    """The HDR crops shipped with the package (svelive/data), for machines without the full images."""
    return Path(str(resources.files("svelive") / "data"))


def find_images(data_dir: Path) -> list[Path]:
    """Sorted EXR files of ``data_dir``; a clear error when there are none."""
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        raise SveliveError(f"{data_dir}: no such directory of HDR images (pass --data DIR)")
    images = sorted(p for p in data_dir.iterdir() if p.suffix.lower() == ".exr")
    if not images:
        raise SveliveError(f"{data_dir}: holds no .exr images")
    return images


def load_scene(path: Path) -> np.ndarray:
    """Linear luminance of an EXR, float32 (H, W), cropped to whole 4x4 blocks, negatives and NaN set to 0."""
    lum = read_luminance(path)
    h, w = lum.shape
    lum = lum[: h - h % 4, : w - w % 4]
    return np.clip(np.nan_to_num(lum, nan=0.0, posinf=0.0, neginf=0.0), 0, None).astype(np.float32)


@dataclass(frozen=True)
class Condition:
    """One benchmark condition: a pattern at a noise level."""

    pattern: str
    noise: str

    def radiance(self, scene: np.ndarray, sensor: Sensor = BENCH_SENSOR) -> np.ndarray:
        """``scene`` in DN at exposure 1 for this condition, float32 (H, W)."""
        scale = exposure_scale(scene, Pattern.parse(self.pattern), sensor,
                               stops_below_fill=NOISE_LEVELS[self.noise])
        return (scene * np.float32(scale)).astype(np.float32)
