"""The speed/accuracy benchmark: every method and setting, over real HDR images, patterns and noise levels.

Accuracy is measured at each image's own resolution; time per frame on the
same scene resized to 1920x1200 (the product's frame size), one OpenCV thread,
median of several runs of the whole public ``reconstruct`` call (as
benchmarks/speed.py). Noise seeds are fixed, so a run is reproducible up to
timing.
"""

from __future__ import annotations

import os
import platform
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from svelive.bench.reference import bracketing_reference
from svelive.bench.scenes import BENCH_SENSOR, NOISE_LEVELS, PATTERNS, Condition, find_images, load_scene
from svelive.core.errors import SveliveError
from svelive.metrics import error_stops_p99, log_psnr, mu_law_psnr, pu21_psnr
from svelive.reconstruction.input import prepare
from svelive.reconstruction.methods import DEFAULT_METHOD, METHODS, baseline
from svelive.reconstruction.methods.base import Estimate, SveInput
from svelive.reconstruction.single import run_method
from svelive.simulation import simulate

TIMING_SIZE = (1200, 1920)  # rows, cols


@dataclass(frozen=True)
class Setting:
    """One marker of the chart: a method with fixed options."""

    label: str
    method: str
    options: tuple[tuple[str, object], ...] = ()

    def run(self, inp: SveInput) -> Estimate:
        """Run on a prepared input (the OpenCV baseline is not a product method, so it is called directly)."""
        if self.method == "baseline":
            return baseline.run(inp)
        return run_method(inp, self.method, **dict(self.options))


def default_settings() -> list[Setting]:
    """Every registered method with default options, its main parameter settings, and the OpenCV baseline."""
    settings = [Setting(name, name) for name in METHODS]
    if "cubic" in METHODS:
        settings.append(Setting("cubic literal", "cubic", (("literal", True),)))
    settings.append(Setting("baseline", "baseline"))
    return settings


@dataclass(frozen=True)
class BenchConfig:
    """What a benchmark run covers."""

    images: tuple[str, ...] = ()  # image stems; empty = every image found
    patterns: tuple[str, ...] = PATTERNS
    noise_levels: tuple[str, ...] = tuple(NOISE_LEVELS)
    repeats: int = 5  # timing runs per setting and condition (median)
    slow_repeats: int = 1  # for settings slower than SLOW_MS
    seed: int = 0


SLOW_MS = 300.0


def quick_config() -> BenchConfig:
    """A couple of minutes: three images, all patterns and noise levels, fewer timing runs."""
    return BenchConfig(images=("Cannon", "Desk", "MtTamWest"), repeats=3, slow_repeats=1)


@dataclass
class Row:
    """One result: a setting on one image, pattern and noise level."""

    method: str
    image: str
    pattern: str
    noise: str
    ms_per_frame: float
    pu21_psnr: float
    log_psnr: float
    mu_law_psnr: float
    error_stops_p99: float
    reference_pu21_psnr: float
    below_reference_db: float = field(init=False)

    def __post_init__(self) -> None:
        self.below_reference_db = self.reference_pu21_psnr - self.pu21_psnr


def accuracy(image: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """The four metrics of the issue for one reconstruction."""
    return {"pu21_psnr": pu21_psnr(image, truth), "log_psnr": log_psnr(image, truth),
            "mu_law_psnr": mu_law_psnr(image, truth), "error_stops_p99": error_stops_p99(image, truth)}


def timing_frame(scene: np.ndarray, condition: Condition, seed: int) -> np.ndarray:
    """The raw frame of ``scene`` resized to 1920x1200 under ``condition``, uint16."""
    big = np.maximum(cv2.resize(scene, TIMING_SIZE[::-1], interpolation=cv2.INTER_CUBIC), 0)
    return simulate(condition.radiance(big), condition.pattern, BENCH_SENSOR, seed=seed).raw


def median_ms(once: Callable[[], object], repeats: int) -> float:
    """Median wall time (ms) of ``once()`` over ``repeats`` runs, after one warm-up run."""
    once()
    times = []
    for _ in range(max(repeats, 1)):
        t = time.perf_counter()
        once()
        times.append(time.perf_counter() - t)
    return float(np.median(times)) * 1e3


def time_reconstruct(setting: Setting, raw: np.ndarray, pattern: str, repeats: int) -> float:
    """Median wall time (ms) of prepare + method on ``raw`` (as ``svelive.reconstruct`` does), one warm-up run."""
    return median_ms(lambda: setting.run(prepare(raw, pattern, BENCH_SENSOR)), repeats)


def machine() -> dict[str, object]:
    """Description of the machine the benchmark ran on."""
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpu": model, "cores": os.cpu_count(), "threads_used": 1, "python": platform.python_version(),
            "numpy": np.__version__, "opencv": cv2.__version__, "system": platform.platform(),
            "load_average_at_start": os.getloadavg() if hasattr(os, "getloadavg") else None}


def run_benchmark(data_dir: Path, config: BenchConfig, settings: list[Setting] | None = None,
                  log: Callable[[str], None] = print) -> dict[str, object]:
    """Run the benchmark; returns {"machine", "config", "rows", "summary"} (JSON-ready)."""
    cv2.setNumThreads(1)
    settings = default_settings() if settings is None else settings
    paths = find_images(data_dir)
    if config.images:
        wanted = {name.lower() for name in config.images}
        paths = [p for p in paths if p.stem.lower() in wanted]
        if not paths:
            raise SveliveError(f"{data_dir}: holds none of the images {', '.join(config.images)}")
    rows: list[Row] = []
    for path in paths:
        scene = load_scene(path)
        for pattern in config.patterns:
            for noise in config.noise_levels:
                condition = Condition(pattern, noise)
                radiance = condition.radiance(scene)
                frame = simulate(radiance, pattern, BENCH_SENSOR, seed=config.seed)
                inp = prepare(frame.raw, pattern, BENCH_SENSOR)
                reference = pu21_psnr(bracketing_reference(radiance, pattern, BENCH_SENSOR, config.seed), frame.truth)
                big = timing_frame(scene, condition, config.seed)
                for setting in settings:
                    metrics = accuracy(setting.run(inp).image, frame.truth)
                    first = time_reconstruct(setting, big, pattern, 0)
                    repeats = config.slow_repeats if first > SLOW_MS else config.repeats
                    ms = first if repeats <= 1 else time_reconstruct(setting, big, pattern, repeats - 1)
                    rows.append(Row(setting.label, path.stem, pattern, noise, ms, reference_pu21_psnr=reference,
                                    **metrics))
                log(f"{path.stem} {pattern} {noise}: " + ", ".join(
                    f"{r.method} {r.pu21_psnr:.1f} dB {r.ms_per_frame:.0f} ms" for r in rows[-len(settings):])
                    + f"; bracketing {reference:.1f} dB")
    return {"machine": machine(), "config": asdict(config), "sensor": _sensor_dict(),
            "default_method": DEFAULT_METHOD, "rows": [asdict(r) for r in rows], "summary": summarise(rows)}


def _sensor_dict() -> dict[str, float]:
    s = BENCH_SENSOR
    return {"bits": s.bits, "white_level": s.white_level, "gain_e_per_dn": s.effective_gain,
            "read_noise_dn": s.effective_read_noise, "full_well_e": s.effective_gain * s.range_dn}


def summarise(rows: list[Row]) -> list[dict[str, object]]:
    """Per setting: mean of every metric over all rows, median time, Pareto membership (time vs PU21)."""
    labels = list(dict.fromkeys(r.method for r in rows))
    out = []
    for label in labels:
        mine = [r for r in rows if r.method == label]
        out.append({
            "method": label,
            "ms_per_frame": float(np.median([r.ms_per_frame for r in mine])),
            "pu21_psnr": float(np.mean([r.pu21_psnr for r in mine])),
            "pu21_psnr_bright": _mean([r.pu21_psnr for r in mine if r.noise == "bright"]),
            "pu21_psnr_dim": _mean([r.pu21_psnr for r in mine if r.noise == "dim"]),
            "log_psnr": float(np.mean([r.log_psnr for r in mine])),
            "mu_law_psnr": float(np.mean([r.mu_law_psnr for r in mine])),
            "error_stops_p99": float(np.mean([r.error_stops_p99 for r in mine])),
            "below_reference_db": float(np.mean([r.below_reference_db for r in mine])),
            "reference_pu21_psnr": float(np.mean([r.reference_pu21_psnr for r in mine])),
        })
    front = pareto_front([(s["ms_per_frame"], s["pu21_psnr"]) for s in out])
    for s, on in zip(out, front):
        s["pareto"] = on
    return out


def _mean(values: list[float]) -> float | None:
    return float(np.mean(values)) if values else None


def pareto_front(points: list[tuple[float, float]]) -> list[bool]:
    """For (time, accuracy) points: True where no other point is at least as fast and as accurate, and better in one."""
    flags = []
    for i, (t, a) in enumerate(points):
        dominated = any((t2 <= t and a2 >= a) and (t2 < t or a2 > a) for j, (t2, a2) in enumerate(points) if j != i)
        flags.append(not dominated)
    return flags
