"""Time per 1920x1200 12-bit frame of every reconstruction method, one thread.

    python benchmarks/speed.py [--repeats 7] [--methods weighted,aggregate] [--pattern 1,4/16,64]

Simulates one frame from a shipped sample scene (upscaled to 1920x1200) and
reports the median wall time of several runs per method. OpenCV is limited to
one thread and numpy's BLAS is not used by the methods, so this is one core.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

import svelive  # noqa: E402
from svelive import Pattern, Sensor  # noqa: E402
from svelive.simulate import exposure_scale, load_sample_scene, simulate  # noqa: E402


def test_frame(pattern: str, size: tuple[int, int] = (1200, 1920)) -> tuple[np.ndarray, Sensor]:
    sensor = Sensor.from_full_well(12, 10_000, 3)
    scene = cv2.resize(load_sample_scene("desk"), size[::-1], interpolation=cv2.INTER_CUBIC)
    scene = np.maximum(scene, 0)
    radiance = scene * exposure_scale(scene, Pattern.parse(pattern), sensor)
    return simulate(radiance, pattern, sensor, seed=0).raw, sensor


def time_method(raw: np.ndarray, pattern: str, sensor: Sensor, method: str, repeats: int) -> float:
    kwargs = dict(method=method, white_level=sensor.white_level, gain=sensor.gain, read_noise=sensor.read_noise)
    svelive.reconstruct(raw, pattern, **kwargs)  # warm caches
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        svelive.reconstruct(raw, pattern, **kwargs)
        times.append(time.perf_counter() - t)
    return float(np.median(times)) * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--pattern", default="1,4/16,64")
    parser.add_argument("--methods", default=",".join(svelive.methods()))
    args = parser.parse_args()
    cv2.setNumThreads(1)
    raw, sensor = test_frame(args.pattern)
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, one thread; "
          f"pattern {args.pattern}, 1920x1200 12-bit, median of {args.repeats}")
    for method in args.methods.split(","):
        repeats = 3 if method == "cubic" else args.repeats
        print(f"{method:12s} {time_method(raw, args.pattern, sensor, method, repeats):8.1f} ms")


if __name__ == "__main__":
    main()
