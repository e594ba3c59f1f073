"""PU21-PSNR of every method on simulated frames of real HDR images.

    python benchmarks/accuracy.py                    # the shipped 256x256 crops
    python benchmarks/accuracy.py --images ../shared/data/hdr/*.exr

12-bit sensor, 10 000 e- full well, 3 e- read noise; "bright" scales each scene
so its brightest point (99.9th percentile) just fills the lowest exposure,
"dim" is 5 stops darker. Prints a Markdown table of means over the images.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import svelive
from svelive import Pattern, Sensor, simulate
from svelive.exr import read_luminance
from svelive.metrics import pu21_psnr
from svelive.simulate import SAMPLE_SCENES, exposure_scale, load_sample_scene

PATTERNS = ("1,4/16,64", "1,2/4,8", "1/1/8/8")
BRIGHTNESS = {"bright": 0.0, "dim": 5.0}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--images", nargs="*", type=Path, help="HDR EXR files (default: the shipped crops)")
    parser.add_argument("--seed", type=int, default=3)
    args = parser.parse_args()
    scenes = ({p.stem: read_luminance(p) for p in args.images} if args.images
              else {name: load_sample_scene(name) for name in SAMPLE_SCENES})
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
                frame = simulate(radiance, pattern, sensor, seed=args.seed)
                for m in methods:
                    image = svelive.reconstruct(frame.raw, pattern, method=m, white_level=sensor.white_level,
                                                gain=sensor.gain, read_noise=sensor.read_noise)
                    scores[m].append(pu21_psnr(image, frame.truth))
            print(f"| {pattern} | {label}, mean of {len(scenes)} | "
                  + " | ".join(f"{np.mean(v):.2f}" for v in scores.values()) + " |", flush=True)


if __name__ == "__main__":
    main()
