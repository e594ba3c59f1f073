"""The colour benchmark: the joint colour reconstruction against the split baseline over RGB HDR images.

For every colour layout of real sensors (svelive.core.camera.COLOUR_LAYOUTS), a
bright and a dim scene (as the mono benchmark: the brightest point just fills
the shortest exposure, or 5 stops below), every RGB image is simulated through
the colour filter and the exposure mosaic with the benchmark sensor, and
reconstructed by each setting:

- ``joint``: the colour default (``colour="joint"``) with a reconstruction method;
- ``split``: the baseline, HDR per CFA channel with that mono method, then demosaicing.

Accuracy (svelive.metrics): PU21-PSNR on luminance (camera RGB taken as linear
sRGB, Rec. 709 luma) and per channel, CIEDE2000 mean and 99th percentile of a
fixed sRGB rendering. Time per frame: the scene resized to 1920x1200, median of
several runs of prepare + reconstruction on one thread, as the mono benchmark.
Images without R, G, B (a luminance-only EXR) are skipped and named in the results; a luminance/chroma
EXR (Y, RY, BY: StarField) is converted to RGB.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from svelive.bench.runner import TIMING_SIZE, median_ms
from svelive.bench.scenes import BENCH_SENSOR, NOISE_LEVELS, find_images
from svelive.core.camera import COLOUR_LAYOUTS, Camera
from svelive.core.errors import SveliveError
from svelive.core.sensor import Sensor
from svelive.exr import read_exr
from svelive.metrics import colour_error, pu21_psnr_colour
from svelive.reconstruction.input import prepare
from svelive.reconstruction.methods import DEFAULT_METHOD
from svelive.reconstruction.methods.base import SveInput
from svelive.reconstruction.single import run_method
from svelive.simulation import SAMPLE_SCENES, exposure_scale, load_sample_scene, simulate

#: Whole tiles of every colour layout (the assorted-pixels tile is 4x4).
CROP = 4


@dataclass(frozen=True)
class ColourSetting:
    """One colour reconstruction: a mode (``joint`` or ``split``) with a method."""

    label: str
    colour: str
    method: str = DEFAULT_METHOD

    def run(self, inp: SveInput) -> np.ndarray:
        """Reconstruct a prepared colour input, float32 (H, W, 3)."""
        return run_method(inp, self.method, colour=self.colour).image


def colour_settings(methods: tuple[str, ...] = (DEFAULT_METHOD, "weighted")) -> list[ColourSetting]:
    """Joint and split for each method; the default method's pair is labelled ``joint`` and ``split``."""
    out = []
    for mode in ("joint", "split"):
        for m in methods:
            out.append(ColourSetting(mode if m == DEFAULT_METHOD else f"{mode} {m}", mode, m))
    return out


#: The issue's comparison: the colour default against the baseline, both with the default method.
DEFAULT_LABEL, BASELINE_LABEL = "joint", "split"


@dataclass(frozen=True)
class ColourBenchConfig:
    """What a colour benchmark run covers."""

    images: tuple[str, ...] = ()  # image stems; empty = every image found
    layouts: tuple[str, ...] = tuple(COLOUR_LAYOUTS)
    noise_levels: tuple[str, ...] = tuple(NOISE_LEVELS)
    repeats: int = 5  # timing runs per setting and condition (median); 0 skips timing
    timed_images: int | None = None  # how many images (the first ones) are timed; None: all
    timed_noise_levels: tuple[str, ...] = ()  # the noise levels timed; empty: all
    seed: int = 0


def quick_colour_config() -> ColourBenchConfig:
    """Well under a minute with the shipped crops: two timing runs, the first image's bright frames only."""
    return ColourBenchConfig(repeats=2, timed_images=1, timed_noise_levels=("bright",))


def crop_rgb(rgb: np.ndarray) -> np.ndarray:
    """``rgb`` cropped to whole 4x4 blocks, negatives, NaN and inf set to 0, float32 (H, W, 3)."""
    h, w = rgb.shape[:2]
    rgb = rgb[: h - h % CROP, : w - w % CROP]
    return np.clip(np.nan_to_num(rgb, nan=0.0, posinf=0.0, neginf=0.0), 0, None).astype(np.float32)


#: Rec. 709 luminance weights of R, G, B (the luminance of a luminance/chroma EXR).
REC709 = (0.2126, 0.7152, 0.0722)


def rgb_from_luminance_chroma(y: np.ndarray, ry: np.ndarray, by: np.ndarray) -> np.ndarray:
    """Linear RGB, float32 (H, W, 3), of a luminance/chroma EXR (OpenEXR's RGBA/YCA form).

    Args:
        y: float32 (H, W), the luminance Y.
        ry, by: float32 (h, w), (R - Y) / Y and (B - Y) / Y, usually subsampled (half size each way);
            upsampled bilinearly to Y's size (pixel centres aligned).

    R = (RY + 1) Y, B = (BY + 1) Y, G = (Y - 0.2126 R - 0.0722 B) / 0.7152.
    """
    h, w = y.shape

    def full(plane: np.ndarray) -> np.ndarray:
        plane = np.asarray(plane, np.float32)
        return plane if plane.shape == (h, w) else cv2.resize(plane, (w, h), interpolation=cv2.INTER_LINEAR)

    y = np.asarray(y, np.float32)
    r, b = (full(ry) + 1) * y, (full(by) + 1) * y
    g = (y - np.float32(REC709[0]) * r - np.float32(REC709[2]) * b) / np.float32(REC709[1])
    return np.stack([r, g, b], axis=-1).astype(np.float32)


def load_rgb(path: Path | str) -> np.ndarray | None:
    """Linear RGB of an EXR, float32 (H, W, 3) cropped as :func:`crop_rgb`: its R, G, B, or converted from
    Y, RY, BY (a luminance/chroma file, :func:`rgb_from_luminance_chroma`); None when it has neither."""
    channels, _ = read_exr(path)
    if all(c in channels for c in "RGB"):
        return crop_rgb(np.stack([channels[c] for c in "RGB"], axis=-1))
    if all(c in channels for c in ("Y", "RY", "BY")):
        return crop_rgb(rgb_from_luminance_chroma(channels["Y"], channels["RY"], channels["BY"]))
    return None


def shipped_scenes() -> dict[str, np.ndarray]:
    """The shipped 256x256 RGB crops by name."""
    return {name: crop_rgb(load_sample_scene(name, rgb=True)) for name in SAMPLE_SCENES}


def data_scenes(data_dir: Path, names: tuple[str, ...] = ()) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """RGB scenes of ``data_dir`` by stem, and the images skipped with the reason."""
    paths = find_images(data_dir)
    if names:
        wanted = {n.lower() for n in names}
        paths = [p for p in paths if p.stem.lower() in wanted]
        if not paths:
            raise SveliveError(f"{data_dir}: holds none of the images {', '.join(names)}")
    scenes, skipped = {}, {}
    for path in paths:
        rgb = load_rgb(path)
        if rgb is None:
            skipped[path.stem] = "luminance only (no R, G, B channels, nor RY and BY)"
        else:
            scenes[path.stem] = rgb
    return scenes, skipped


@dataclass(frozen=True)
class ColourCondition:
    """One condition: a colour layout at a noise level."""

    layout: str
    noise: str

    @property
    def pattern(self) -> str:
        return COLOUR_LAYOUTS[self.layout][0]

    @property
    def cfa(self) -> str:
        return COLOUR_LAYOUTS[self.layout][1]

    def camera(self, sensor: Sensor = BENCH_SENSOR) -> Camera:
        return Camera.build(self.layout, sensor=sensor)

    def radiance(self, scene: np.ndarray, sensor: Sensor = BENCH_SENSOR) -> np.ndarray:
        """``scene`` in DN at exposure 1, float32 (H, W, 3).

        Bright: the 99.9th percentile of every pixel's brightest channel just fills the
        shortest exposure (the mono definition with the brightest channel for luminance,
        svelive.simulation.exposure_scale); dim: 5 stops below.
        """
        scale = exposure_scale(scene, self.camera(sensor).require_pattern(), sensor,
                               stops_below_fill=NOISE_LEVELS[self.noise])
        return (scene * np.float32(scale)).astype(np.float32)

    def simulate(self, radiance: np.ndarray, seed: int, sensor: Sensor = BENCH_SENSOR):
        """The raw frame of ``radiance`` (H, W, 3) through this layout; a SimulatedFrame with RGB truth."""
        return simulate(radiance, self.pattern, sensor, cfa=self.cfa, seed=seed)


@dataclass
class ColourRow:
    """One result: a setting on one image, layout and noise level."""

    method: str
    image: str
    layout: str
    noise: str
    ms_per_frame: float | None
    pu21_y: float
    pu21_r: float
    pu21_g: float
    pu21_b: float
    de2000_mean: float
    de2000_p99: float


def colour_accuracy(image: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """PU21-PSNR of luminance and channels, CIEDE2000 mean and p99, for one reconstruction."""
    pu = pu21_psnr_colour(image, truth)
    return {"pu21_y": pu["Y"], "pu21_r": pu["R"], "pu21_g": pu["G"], "pu21_b": pu["B"], **colour_error(image, truth)}


def time_colour(setting: ColourSetting, raw: np.ndarray, camera: Camera, repeats: int) -> float:
    """Median wall time (ms) of prepare + reconstruction of ``raw``, after one warm-up run."""
    return median_ms(lambda: setting.run(prepare(raw, camera)), repeats)


def timing_frame(scene: np.ndarray, condition: ColourCondition, seed: int) -> np.ndarray:
    """The raw frame of ``scene`` resized to 1920x1200 under ``condition``, uint16."""
    big = np.maximum(cv2.resize(scene, TIMING_SIZE[::-1], interpolation=cv2.INTER_CUBIC), 0)
    return condition.simulate(condition.radiance(big), seed).raw


def run_colour_benchmark(scenes: dict[str, np.ndarray], config: ColourBenchConfig,
                         settings: list[ColourSetting] | None = None, skipped: dict[str, str] | None = None,
                         log: Callable[[str], None] = print) -> dict[str, object]:
    """Run the colour benchmark over RGB ``scenes`` (name -> float (H, W, 3)); JSON-ready results."""
    cv2.setNumThreads(1)
    settings = colour_settings() if settings is None else settings
    if not scenes:
        raise SveliveError("no RGB images for the colour benchmark")
    rows: list[ColourRow] = []
    for index, (name, scene) in enumerate(scenes.items()):
        timed = config.repeats > 0 and (config.timed_images is None or index < config.timed_images)
        for layout in config.layouts:
            for noise in config.noise_levels:
                condition = ColourCondition(layout, noise)
                camera = condition.camera()
                frame = condition.simulate(condition.radiance(scene), config.seed)
                inp = prepare(frame.raw, camera)
                timed_here = timed and (not config.timed_noise_levels or noise in config.timed_noise_levels)
                big = timing_frame(scene, condition, config.seed) if timed_here else None
                for setting in settings:
                    metrics = colour_accuracy(setting.run(inp), frame.truth)
                    ms = None if big is None else time_colour(setting, big, camera, config.repeats)
                    rows.append(ColourRow(setting.label, name, layout, noise, ms, **metrics))
                log(f"colour {name} {layout} {noise}: " + ", ".join(
                    f"{r.method} {r.pu21_y:.1f} dB dE {r.de2000_mean:.2f}"
                    + ("" if r.ms_per_frame is None else f" {r.ms_per_frame:.0f} ms")
                    for r in rows[-len(settings):]))
    default, baseline = DEFAULT_LABEL, BASELINE_LABEL
    return {"config": asdict(config), "images": list(scenes), "skipped": skipped or {},
            "default": default, "baseline": baseline, "rows": [asdict(r) for r in rows],
            "summary": summarise_colour(rows), "comparison": compare(rows, default, baseline)}


METRICS = ("pu21_y", "pu21_r", "pu21_g", "pu21_b", "de2000_mean", "de2000_p99")


def summarise_colour(rows: list[ColourRow]) -> list[dict[str, object]]:
    """Per setting: the mean of every metric over all rows, bright and dim luminance PU21, median time."""
    out = []
    for label in dict.fromkeys(r.method for r in rows):
        mine = [r for r in rows if r.method == label]
        times = [r.ms_per_frame for r in mine if r.ms_per_frame is not None]
        entry: dict[str, object] = {"method": label, "ms_per_frame": float(np.median(times)) if times else None}
        for m in METRICS:
            entry[m] = float(np.mean([getattr(r, m) for r in mine]))
        for noise in dict.fromkeys(r.noise for r in mine):
            entry[f"pu21_y_{noise}"] = float(np.mean([r.pu21_y for r in mine if r.noise == noise]))
        out.append(entry)
    return out


@dataclass
class Comparison:
    """The issue's target on one layout and noise level (means over the images)."""

    layout: str
    noise: str
    pu21_y_default: float
    pu21_y_baseline: float
    de2000_mean_default: float
    de2000_mean_baseline: float
    de2000_p99_default: float
    de2000_p99_baseline: float
    gain_db: float = field(init=False)
    met: bool = field(init=False)

    def __post_init__(self) -> None:
        self.gain_db = self.pu21_y_default - self.pu21_y_baseline
        self.met = self.gain_db >= 2.0 and self.de2000_mean_default < self.de2000_mean_baseline


def compare(rows: list[ColourRow], default: str, baseline: str) -> list[dict[str, object]]:
    """Default against baseline per layout and noise level, then overall (layout and noise ``all``)."""
    labels = {r.method for r in rows}
    if default not in labels or baseline not in labels:
        return []
    groups = [(layout, noise) for layout in dict.fromkeys(r.layout for r in rows)
              for noise in dict.fromkeys(r.noise for r in rows)] + [("all", "all")]
    out = []
    for layout, noise in groups:
        def mean(label: str, metric: str) -> float:
            return float(np.mean([getattr(r, metric) for r in rows if r.method == label
                                  and layout in ("all", r.layout) and noise in ("all", r.noise)]))

        out.append(asdict(Comparison(layout, noise, mean(default, "pu21_y"), mean(baseline, "pu21_y"),
                                     mean(default, "de2000_mean"), mean(baseline, "de2000_mean"),
                                     mean(default, "de2000_p99"), mean(baseline, "de2000_p99"))))
    return out


def markdown_colour(results: dict[str, object]) -> str:
    """The summary and the default-against-baseline table as Markdown."""
    lines = ["| setting | ms / frame | PU21 Y | Y bright | Y dim | PU21 R | PU21 G | PU21 B | dE2000 mean | dE2000 p99 |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for s in results["summary"]:
        ms = "-" if s["ms_per_frame"] is None else f"{s['ms_per_frame']:.1f}"
        lines.append(f"| {s['method']} | {ms} | {s['pu21_y']:.2f} | {_f(s.get('pu21_y_bright'))} |"
                     f" {_f(s.get('pu21_y_dim'))} | {s['pu21_r']:.2f} | {s['pu21_g']:.2f} | {s['pu21_b']:.2f} |"
                     f" {s['de2000_mean']:.2f} | {s['de2000_p99']:.2f} |")
    lines += ["", f"{results['default']} against {results['baseline']} (target: +2 dB PU21 on luminance and a "
                  "lower mean CIEDE2000):", "",
              "| layout | noise | PU21 Y default | baseline | gain (dB) | dE2000 mean default | baseline |"
              " dE2000 p99 default | baseline | target |",
              "|---|---|---:|---:|---:|---:|---:|---:|---:|---|"]
    for c in results["comparison"]:
        lines.append(f"| {c['layout']} | {c['noise']} | {c['pu21_y_default']:.2f} | {c['pu21_y_baseline']:.2f} |"
                     f" {c['gain_db']:+.2f} | {c['de2000_mean_default']:.2f} | {c['de2000_mean_baseline']:.2f} |"
                     f" {c['de2000_p99_default']:.2f} | {c['de2000_p99_baseline']:.2f} |"
                     f" {'met' if c['met'] else 'not met'} |")
    if results.get("skipped"):
        lines += ["", "Skipped: " + "; ".join(f"{k} ({v})" for k, v in results["skipped"].items())]
    return "\n".join(lines) + "\n"


def _f(value: float | None) -> str:
    return "-" if value is None else f"{value:.2f}"
