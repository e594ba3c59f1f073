"""The live chart: each step of the live ladder, its speed on this machine against its accuracy.

For every step of :data:`svelive.reconstruction.live.LADDER` (a method with or
without temporal fusion), monochrome (the bench's patterns) and colour (the
colour layouts of real sensors, dual-ISO by default), two measurements of an
ordinary ``svelive.Reconstructor(camera, method=..., temporal=..., workers=..., refresh=...)`` with the live
service's band refresh (:data:`svelive.reconstruction.live.LIVE_REFRESH`, which only monochrome ``adaptive`` with
fusion takes: the top step as the service runs it):

- **speed**: a still scene (a bench image resized to the live frame size,
  1920x1200 by default, as the bench's timing frames) rendered as a sequence of
  raw frames with new noise in each; wall time and the process's CPU time (every
  thread: the stream's strip pool too) of ``process`` per frame, median over the
  frames after the warm-up ones (enough for the band refresh to settle); fps = 1000 / median wall ms. Times depend on the
  machine and its load, which the results record.
- **accuracy**: PU21-PSNR (luminance PU21 for colour, svelive.metrics) of the
  stream's output for the last of ``frames`` frames of a static scene (new noise
  in each, so fusion shows what it gains) against the simulator's truth, on the
  bench's images at their own size under its noise levels (bright and dim,
  svelive.bench.scenes.NOISE_LEVELS) with its sensor. Noise seeds are fixed:
  accuracy repeats exactly.
"""

from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Sequence

import cv2
import numpy as np

from svelive.bench.colour import ColourCondition, crop_rgb, data_scenes, shipped_scenes
from svelive.bench.runner import TIMING_SIZE, machine
from svelive.bench.scenes import BENCH_SENSOR, NOISE_LEVELS, PATTERNS, Condition, find_images, load_scene
from svelive.core.camera import COLOUR_LAYOUTS, Camera
from svelive.core.errors import SveliveError
from svelive.metrics import pu21_psnr, pu21_psnr_colour
from svelive.reconstruction import Reconstructor
from svelive.reconstruction.live import LADDER, LIVE_REFRESH, LiveStep
from svelive.simulation import SAMPLE_SCENES, sample_scene_path, simulate

#: The colour layout the live chart measures by default: the colour demo camera's.
LIVE_COLOUR_LAYOUTS: tuple[str, ...] = ("dual-iso",)

#: The live target, frames per second.
REALTIME_FPS = 30.0


@dataclass(frozen=True)
class LiveBenchConfig:
    """What a live-chart run covers.

    ``timing_size``: (rows, cols) of the timed frames; ``timing_frames``: frames per timed
    sequence, of which the first ``warmup`` are not counted (the band refresh runs every band
    until a band's history settles); ``timed_images``: how many scenes (the first ones) are
    timed, under every noise level; ``frames``: the static frames fused before the accuracy is
    scored; ``refresh``: the streams' ``Reconstructor(refresh=...)``, the service's by default.
    """

    mono_patterns: tuple[str, ...] = PATTERNS
    colour_layouts: tuple[str, ...] = LIVE_COLOUR_LAYOUTS
    noise_levels: tuple[str, ...] = tuple(NOISE_LEVELS)
    frames: int = 8
    timing_size: tuple[int, int] = TIMING_SIZE
    timing_frames: int = 16
    warmup: int = 8
    timed_images: int = 1
    workers: int = 2
    opencv_threads: int = 1
    seed: int = 0
    refresh: int = LIVE_REFRESH

    def __post_init__(self) -> None:
        if self.frames < 1 or self.timing_frames <= self.warmup or self.warmup < 0 or self.timed_images < 1:
            raise SveliveError("the live chart needs frames >= 1, timed_images >= 1 and more timing frames "
                               f"than warm-up ones (got {self.frames}, {self.timed_images}, "
                               f"{self.timing_frames} and {self.warmup})")
        unknown = [name for name in self.colour_layouts if name not in COLOUR_LAYOUTS]
        if unknown:
            raise SveliveError(f"unknown colour layout {unknown[0]!r}; choose from {', '.join(COLOUR_LAYOUTS)}")


def quick_live_config() -> LiveBenchConfig:
    """Under a minute with the shipped crops: 960x600 timed frames, 4 counted after 8 warm-up, one pattern."""
    return LiveBenchConfig(mono_patterns=PATTERNS[:1], timing_size=(600, 960), timing_frames=12, warmup=8)


def kind_of(case: str) -> str:
    """``"colour"`` for a colour layout name (svelive.core.camera.COLOUR_LAYOUTS), else ``"mono"`` (a pattern)."""
    return "colour" if case in COLOUR_LAYOUTS else "mono"


def case_camera(case: str) -> Camera:
    """The bench sensor behind a mono exposure pattern or a colour layout."""
    return Camera.build(case, sensor=BENCH_SENSOR)


def case_radiance(case: str, noise: str, scene: np.ndarray) -> np.ndarray:
    """``scene`` (float (H, W) luminance, or (H, W, 3) RGB for a colour layout) in DN at exposure 1 under the
    bench's noise level ``noise``, float32 of the same shape (svelive.bench Condition / ColourCondition)."""
    condition = ColourCondition(case, noise) if kind_of(case) == "colour" else Condition(case, noise)
    return condition.radiance(scene)


def static_frames(radiance: np.ndarray, camera: Camera, count: int, seed: int) -> tuple[list[np.ndarray], np.ndarray]:
    """``count`` raw frames (uint16 (H, W)) of a still scene, new noise in each (seeds ``seed``, ``seed + 1``, ...),
    and their truth (float32 (H, W), or (H, W, 3) camera RGB with a colour filter; DN at exposure 1)."""
    frames = [simulate(radiance, camera.require_pattern(), camera.sensor, cfa=camera.cfa, seed=seed + i)
              for i in range(count)]
    return [f.raw for f in frames], frames[0].truth


def resized(scene: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``scene`` resized to ``size`` (rows, cols) as the bench's timing frames are (cubic, negatives set to 0)."""
    return np.maximum(cv2.resize(scene, size[::-1], interpolation=cv2.INTER_CUBIC), 0)


def stream(step: LiveStep, camera: Camera, workers: int, refresh: int = LIVE_REFRESH) -> Reconstructor:
    """The live step's stream: an ordinary Reconstructor with the step's method and fusion, and the band refresh
    (which only monochrome ``adaptive`` with fusion takes)."""
    return Reconstructor(camera, method=step.method, temporal=step.temporal, workers=workers, refresh=refresh)


def time_step(step: LiveStep, camera: Camera, frames: Sequence[np.ndarray], warmup: int,
              workers: int, refresh: int = LIVE_REFRESH) -> tuple[list[float], list[float]]:
    """Wall and process CPU time (ms; CPU summed over every thread) of each frame after the first ``warmup``,
    one stream over ``frames`` in order."""
    walls, cpus = [], []
    with stream(step, camera, workers, refresh) as s:
        for raw in frames:
            wall, cpu = time.perf_counter(), time.process_time()
            s.process(raw)
            walls.append((time.perf_counter() - wall) * 1e3)
            cpus.append((time.process_time() - cpu) * 1e3)
    return walls[warmup:], cpus[warmup:]


def score(image: np.ndarray, truth: np.ndarray) -> float:
    """PU21-PSNR (dB) of a reconstruction: of luminance for colour (H, W, 3), else of the image (H, W)."""
    return pu21_psnr_colour(image, truth)["Y"] if image.ndim == 3 else pu21_psnr(image, truth)


def step_accuracy(step: LiveStep, camera: Camera, frames: Sequence[np.ndarray], truth: np.ndarray,
                  workers: int, refresh: int = LIVE_REFRESH) -> float:
    """PU21-PSNR (dB) of the step's output for the last of ``frames`` (a static scene) against ``truth``.
    Without fusion a frame's output has no history (and the bench sensor gives the stream its noise model, so
    nothing else is learnt over frames), so only the last frame is reconstructed."""
    with stream(step, camera, workers, refresh) as s:
        for raw in frames if step.temporal else frames[-1:]:
            image = s.process(raw).image
    return score(image, truth)


@dataclass(frozen=True)
class StillSequence:
    """One simulated still scene of a case: an image under a noise level, its raw frames and truth."""

    image: str
    noise: str
    frames: list[np.ndarray]
    truth: np.ndarray | None = None


def accuracy_sequences(case: str, scenes: dict[str, np.ndarray], config: LiveBenchConfig) -> list[StillSequence]:
    """Every scene under every noise level at its own size, ``config.frames`` frames each."""
    camera = case_camera(case)
    out = []
    for name, scene in scenes.items():
        for noise in config.noise_levels:
            frames, truth = static_frames(case_radiance(case, noise, scene), camera, config.frames, config.seed)
            out.append(StillSequence(name, noise, frames, truth))
    return out


def timing_sequences(case: str, scenes: dict[str, np.ndarray], config: LiveBenchConfig) -> list[StillSequence]:
    """The first ``config.timed_images`` scenes resized to the timing size, under every noise level."""
    camera = case_camera(case)
    out = []
    for name in list(scenes)[: config.timed_images]:
        big = resized(scenes[name], config.timing_size)
        for noise in config.noise_levels:
            frames, _ = static_frames(case_radiance(case, noise, big), camera, config.timing_frames, config.seed)
            out.append(StillSequence(name, noise, frames))
    return out


@dataclass
class LiveRow:
    """One step of the ladder on one case (or a kind's cases pooled): speed and accuracy.

    fps: 1000 / ``wall_ms``; wall_ms, cpu_ms: medians over the timed frames (CPU of every thread);
    pu21*: mean PU21-PSNR (dB) over the scenes (and noise levels), None where a level was not run.
    """

    step: str
    kind: str
    camera: str
    fps: float
    wall_ms: float
    cpu_ms: float
    pu21: float
    pu21_bright: float | None
    pu21_dim: float | None
    timed_frames: int
    scored: int


def _mean(values: list[float]) -> float | None:
    return float(np.mean(values)) if values else None


def pooled_row(step: str, kind: str, camera: str, walls: list[float], cpus: list[float],
               scores: list[tuple[str, float]]) -> LiveRow:
    """A row from per-frame times (ms) and (noise level, PU21 dB) scores."""
    wall = float(np.median(walls))
    return LiveRow(step, kind, camera, 1e3 / wall, wall, float(np.median(cpus)), float(np.mean([v for _, v in scores])),
                   _mean([v for n, v in scores if n == "bright"]), _mean([v for n, v in scores if n == "dim"]),
                   len(walls), len(scores))


def run_case(case: str, scenes: dict[str, np.ndarray], config: LiveBenchConfig, ladder: Sequence[LiveStep],
             log: Callable[[str], None]) -> list[dict[str, object]]:
    """Every step of ``ladder`` on one case: one record per step with its per-frame times and per-scene scores."""
    camera = case_camera(case)
    scored, timed = accuracy_sequences(case, scenes, config), timing_sequences(case, scenes, config)
    records = []
    for step in ladder:
        walls, cpus = [], []
        for seq in timed:
            w, c = time_step(step, camera, seq.frames, config.warmup, config.workers, config.refresh)
            walls += w
            cpus += c
        scores = [{"image": seq.image, "noise": seq.noise,
                   "pu21": step_accuracy(step, camera, seq.frames, seq.truth, config.workers, config.refresh)}
                  for seq in scored]
        record = {"step": step.name, "kind": kind_of(case), "camera": case, "wall_ms": walls, "cpu_ms": cpus,
                  "scores": scores}
        row = row_of(step.name, kind_of(case), case, [record])
        log(f"live {kind_of(case)} {case} {step.name}: {row.fps:.1f} fps ({row.wall_ms:.0f} ms,"
            f" CPU {row.cpu_ms:.0f} ms), PU21 {_f(row.pu21_bright)} bright, {_f(row.pu21_dim)} dim")
        records.append(record)
    return records


def row_of(step: str, kind: str, camera: str, records: list[dict[str, object]]) -> LiveRow:
    """A row pooling ``records`` (run_case's): every timed frame and every score."""
    return pooled_row(step, kind, camera, [w for r in records for w in r["wall_ms"]],
                      [c for r in records for c in r["cpu_ms"]],
                      [(s["noise"], s["pu21"]) for r in records for s in r["scores"]])


def summarise_live(records: list[dict[str, object]]) -> tuple[list[LiveRow], list[LiveRow]]:
    """(one row per step and kind, the kind's cases pooled; one row per step and case), in ladder order."""
    cases = [row_of(r["step"], r["kind"], r["camera"], [r]) for r in records]
    pooled = []
    for kind in dict.fromkeys(r["kind"] for r in records):
        mine = [r for r in records if r["kind"] == kind]
        for step in dict.fromkeys(r["step"] for r in mine):
            group = [r for r in mine if r["step"] == step]
            pooled.append(row_of(step, kind, ", ".join(r["camera"] for r in group), group))
    return pooled, cases


def run_live_benchmark(mono: dict[str, np.ndarray], colour: dict[str, np.ndarray], config: LiveBenchConfig,
                       ladder: Sequence[LiveStep] = LADDER,
                       log: Callable[[str], None] = print) -> dict[str, object]:
    """The live chart's measurements: mono ``scenes`` (name -> float32 (H, W) luminance) under every pattern of
    ``config``, colour ones (name -> (H, W, 3) RGB) under every layout (a kind without scenes is skipped and
    named in ``skipped``); JSON-ready results with ``rows`` (step x kind), ``cases`` (step x pattern or layout)
    and ``records`` (per-frame times, per-scene scores)."""
    wanted = [(p, mono) for p in config.mono_patterns] + [(c, colour) for c in config.colour_layouts]
    cases = [(case, scenes) for case, scenes in wanted if scenes]
    if not cases:
        raise SveliveError("no scenes for the live chart (mono needs luminance images, colour RGB ones)")
    threads = cv2.getNumThreads()
    cv2.setNumThreads(config.opencv_threads)
    load_start = _load()
    try:
        records = [r for case, scenes in cases for r in run_case(case, scenes, config, ladder, log)]
    finally:
        cv2.setNumThreads(threads)
    rows, per_case = summarise_live(records)
    return {"machine": {**machine(), "threads_used": config.workers, "load_average_at_start": load_start,
                        "load_average_at_end": _load()},
            "config": asdict(config), "ladder": [asdict(s) | {"name": s.name} for s in ladder],
            "mono_images": list(mono), "colour_images": list(colour), "sensor_bits": BENCH_SENSOR.bits,
            "skipped": [case for case, scenes in wanted if not scenes],
            "rows": [asdict(r) for r in rows], "cases": [asdict(r) for r in per_case], "records": records}


def _load() -> list[float] | None:
    return list(os.getloadavg()) if hasattr(os, "getloadavg") else None


def live_scenes(data: Path | None, images: tuple[str, ...] = ()) -> tuple[dict[str, np.ndarray],
                                                                         dict[str, np.ndarray], str]:
    """(mono scenes, colour scenes, where from): the HDR images of ``data`` (``images`` only, if given; colour
    from those with R, G, B), or with ``data`` None the shipped 256x256 crops (svelive/data)."""
    if data is None:
        mono = {name: load_scene(sample_scene_path(name)) for name in SAMPLE_SCENES}
        return mono, shipped_scenes(), "shipped 256x256 crops"
    wanted = {name.lower() for name in images}
    paths = [p for p in find_images(data) if not wanted or p.stem.lower() in wanted]
    if not paths:
        raise SveliveError(f"{data}: holds none of the images {', '.join(images)}")
    colour, _ = data_scenes(data, tuple(p.stem for p in paths))
    return {p.stem: load_scene(p) for p in paths}, colour, str(data)


def cropped_scenes(scenes: dict[str, np.ndarray], size: tuple[int, int]) -> dict[str, np.ndarray]:
    """Each scene's top-left ``size`` (rows, cols; whole 4x4 tiles), for tiny runs; RGB scenes stay RGB."""
    rows, cols = size
    return {name: crop_rgb(s[:rows, :cols]) if s.ndim == 3 else np.ascontiguousarray(s[:rows, :cols])
            for name, s in scenes.items()}


def _f(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"


def markdown_live(results: dict[str, object]) -> str:
    """The step x kind table, the step x case table, and one verdict line on the live target, as Markdown."""
    rows = results["rows"]
    head = ("| step | frames | fps | ms / frame | CPU ms / frame | PU21-PSNR | bright | dim |\n"
            "|---|---|---:|---:|---:|---:|---:|---:|\n")

    def line(r: dict[str, object], label: str) -> str:
        return (f"| {r['step']} | {label} | {r['fps']:.1f} | {r['wall_ms']:.1f} | {r['cpu_ms']:.1f} |"
                f" {r['pu21']:.2f} | {_f(r['pu21_bright'])} | {_f(r['pu21_dim'])} |")

    text = head + "\n".join(line(r, r["kind"]) for r in rows) + "\n"
    if len(results["cases"]) > len(rows):
        text += "\n" + head + "\n".join(line(r, r["camera"]) for r in results["cases"]) + "\n"
    skipped = results.get("skipped") or []
    note = f"\nSkipped (no scenes of that kind): {', '.join(skipped)}\n" if skipped else ""
    return text + "\n" + verdict(results) + "\n" + note


def verdict(results: dict[str, object]) -> str:
    """One line: which steps reach 30 fps at the timed size, per kind, and the load the run saw."""
    size, workers = results["config"]["timing_size"], results["config"]["workers"]
    parts = []
    for kind in dict.fromkeys(r["kind"] for r in results["rows"]):
        mine = [r for r in results["rows"] if r["kind"] == kind]
        fast = [r["step"] for r in mine if r["fps"] >= REALTIME_FPS]
        best = max(mine, key=lambda r: r["fps"])
        fastest = f"none (fastest {best['step']} {best['fps']:.1f} fps)"
        parts.append(f"{kind} " + (", ".join(fast) if fast else fastest))
    load = results["machine"].get("load_average_at_start")
    return (f"live ladder at {size[1]}x{size[0]}, {workers} workers: {REALTIME_FPS:g} fps reached by "
            + "; ".join(parts) + ("" if load is None else f" (load {load[0]:.2f} at start)"))


def csv_rows(results: dict[str, object]) -> list[dict[str, object]]:
    """The rows for live.csv: each step x kind (what the chart shows), then each step x case a kind pools."""
    shown = {(r["step"], r["camera"]) for r in results["rows"]}
    return results["rows"] + [r for r in results["cases"] if (r["step"], r["camera"]) not in shown]
