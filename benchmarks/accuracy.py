"""PU21-PSNR of every method on simulated frames of real HDR images; with --colour, joint against split.

    python benchmarks/accuracy.py                    # the shipped 256x256 crops
    python benchmarks/accuracy.py --images ../shared/data/hdr/*.exr
    python benchmarks/accuracy.py --colour           # every colour layout, the shipped RGB crops

12-bit sensor, 10 000 e- full well, 3 e- read noise; "bright" scales each scene
so its brightest point (99.9th percentile; of the brightest channel in colour)
just fills the lowest exposure, "dim" is 5 stops darker. Prints a Markdown
table of means over the images. Colour: PU21-PSNR on luminance (camera RGB
taken as linear sRGB, Rec. 709 luma) and per channel, CIEDE2000 of a fixed sRGB
rendering (svelive/metrics.py), for the joint default and the split baseline
with each method given (cubic is left out unless named: seconds per frame).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # this checkout, not an editable install's

import svelive  # noqa: E402
from svelive import Pattern, Sensor, simulate  # noqa: E402
from svelive.exr import read_luminance  # noqa: E402
from svelive.metrics import pu21_psnr  # noqa: E402
from svelive.simulation import SAMPLE_SCENES, exposure_scale, load_sample_scene  # noqa: E402

PATTERNS = ("1,4/16,64", "1,2/4,8", "1/1/8/8")
BRIGHTNESS = {"bright": 0.0, "dim": 5.0}


def mono(scenes: dict[str, np.ndarray], seed: int) -> None:
    sensor = Sensor.from_full_well(12, 10_000, 3)
    methods = svelive.methods()
    print("| pattern | scene | " + " | ".join(methods) + " |")
    print("| --- | --- | " + " | ".join("---" for _ in methods) + " |")
    for pattern in PATTERNS:
        for label, stops in BRIGHTNESS.items():
            scores = {m: [] for m in methods}
            for scene in scenes.values():
                scene = np.maximum(scene, 0)
                radiance = scene * exposure_scale(scene, Pattern.parse(pattern), sensor, stops_below_fill=stops)
                frame = simulate(radiance, pattern, sensor, seed=seed)
                for m in methods:
                    image = svelive.reconstruct(frame.raw, pattern, method=m, white_level=sensor.white_level,
                                                gain=sensor.gain, read_noise=sensor.read_noise)
                    scores[m].append(pu21_psnr(image, frame.truth))
            print(f"| {pattern} | {label}, mean of {len(scenes)} | "
                  + " | ".join(f"{np.mean(v):.2f}" for v in scores.values()) + " |", flush=True)


def colour(scenes: dict[str, np.ndarray], seed: int, methods: list[str]) -> None:
    from svelive.bench.colour import ColourCondition, ColourSetting, colour_accuracy
    from svelive.core.camera import COLOUR_LAYOUTS
    from svelive.reconstruction.input import prepare

    settings = [ColourSetting(f"{mode} {m}", mode, m) for m in methods for mode in ("joint", "split")]
    print(f"# mean of {len(scenes)} scenes: {', '.join(scenes)}; seed {seed}")
    print("| layout | scene | setting | PU21 Y | PU21 R | PU21 G | PU21 B | dE2000 mean | dE2000 p99 |")
    print("| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    for layout in COLOUR_LAYOUTS:
        for noise in BRIGHTNESS:
            condition = ColourCondition(layout, noise)
            scores: dict[str, list[dict[str, float]]] = {s.label: [] for s in settings}
            for scene in scenes.values():
                frame = condition.simulate(condition.radiance(scene), seed)
                inp = prepare(frame.raw, condition.camera())
                for s in settings:
                    scores[s.label].append(colour_accuracy(s.run(inp), frame.truth))
            for label, rows in scores.items():
                mean = {k: float(np.mean([r[k] for r in rows])) for k in rows[0]}
                print(f"| {layout} | {noise} | {label} | {mean['pu21_y']:.2f} | {mean['pu21_r']:.2f} |"
                      f" {mean['pu21_g']:.2f} | {mean['pu21_b']:.2f} | {mean['de2000_mean']:.2f} |"
                      f" {mean['de2000_p99']:.2f} |", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", nargs="*", type=Path, help="HDR EXR files (default: the shipped crops)")
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--colour", action="store_true", help="colour layouts: joint against split")
    parser.add_argument("--methods", default="adaptive,weighted,aggregate",
                        help="with --colour: the methods inside joint and split (comma-separated)")
    args = parser.parse_args()
    if args.colour:
        from svelive.bench.colour import crop_rgb, load_rgb

        if args.images:
            loaded = {p.stem: load_rgb(p) for p in args.images}
            skipped = [name for name, rgb in loaded.items() if rgb is None]
            if skipped:
                print(f"# skipped (luminance only): {', '.join(skipped)}")
            scenes = {name: rgb for name, rgb in loaded.items() if rgb is not None}
        else:
            scenes = {name: crop_rgb(load_sample_scene(name, rgb=True)) for name in SAMPLE_SCENES}
        colour(scenes, args.seed, args.methods.split(","))
        return
    scenes = ({p.stem: read_luminance(p) for p in args.images} if args.images
              else {name: load_sample_scene(name) for name in SAMPLE_SCENES})
    mono(scenes, args.seed)


if __name__ == "__main__":
    main()
