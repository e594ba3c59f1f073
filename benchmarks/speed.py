"""Time per 1920x1200 12-bit frame of every reconstruction method, one thread; with --colour, colour too.

    python benchmarks/speed.py [--repeats 7] [--methods weighted,aggregate] [--pattern 1,4/16,64]
    python benchmarks/speed.py --colour [--layout dual-iso] [--colour-methods adaptive,weighted]
    python benchmarks/speed.py --bench [DIR] [--methods adaptive] [--repeats 5]

Simulates one frame from a shipped sample scene (upscaled to 1920x1200) and
reports the median wall time of several runs per method. OpenCV is limited to
one thread and numpy's BLAS is not used by the methods, so this is one core.
With --colour the mono methods are timed as without it (so that a mono
regression shows in the same run), then a 12-bit colour SVE frame of the
layout (svelive.core.camera.COLOUR_LAYOUTS; the shipped RGB crop upscaled) is
reconstructed joint and split with each colour method. With --bench, each method
is timed instead on the benchmark's own timing frames (svelive.bench: every HDR
image of DIR, default ../shared/data/hdr, under every pattern and noise level,
resized to 1920x1200), prepare + method as the benchmark times them: one line per
frame, then the median and the worst over the frames; --clock thread counts this
thread's CPU time only, which other processes on a shared machine do not inflate.

The process first keeps the memory it frees (svelive.memory.keep_freed_memory), as `svelive serve` and
`svelive reconstruct-sequence` do: with glibc's defaults the heap's top is trimmed after a run and faulted back
in by the next, which on some frames cost more than the method's own extra work (4000-4600 page faults a run,
docs/benchmarks.md, worst89). --default-malloc times with glibc's defaults instead.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # this checkout, not an editable install's

import svelive  # noqa: E402
from svelive import Pattern, Sensor  # noqa: E402
from svelive.core.camera import COLOUR_LAYOUTS  # noqa: E402
from svelive.simulation import exposure_scale, load_sample_scene, simulate  # noqa: E402

SIZE = (1200, 1920)
SENSOR = Sensor.from_full_well(12, 10_000, 3)


def test_frame(pattern: str, size: tuple[int, int] = SIZE, cfa: str | None = None) -> tuple[np.ndarray, Sensor]:
    """The shipped 'desk' crop upscaled to ``size``, bright, through ``pattern`` (and ``cfa``: RGB scene)."""
    scene = cv2.resize(load_sample_scene("desk", rgb=cfa is not None), size[::-1], interpolation=cv2.INTER_CUBIC)
    scene = np.maximum(scene, 0)
    radiance = scene * exposure_scale(scene, Pattern.parse(pattern), SENSOR)
    return simulate(radiance, pattern, SENSOR, cfa=cfa, seed=0).raw, SENSOR


def time_call(run, repeats: int) -> float:
    """Median wall time (ms) of ``run()`` over ``repeats`` runs after one warm-up run."""
    run()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        run()
        times.append(time.perf_counter() - t)
    return float(np.median(times)) * 1e3


def time_method(raw: np.ndarray, pattern: str, sensor: Sensor, method: str, repeats: int, **kwargs) -> float:
    kwargs.update(method=method, white_level=sensor.white_level, gain=sensor.gain, read_noise=sensor.read_noise)
    return time_call(lambda: svelive.reconstruct(raw, pattern, **kwargs), repeats)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--pattern", default="1,4/16,64")
    parser.add_argument("--methods", default=",".join(svelive.methods()))
    parser.add_argument("--colour", action="store_true", help="also time colour frames, joint and split")
    parser.add_argument("--layout", default="dual-iso", choices=list(COLOUR_LAYOUTS))
    parser.add_argument("--colour-methods", default="adaptive,weighted")
    parser.add_argument("--bench", nargs="?", const="", default=None, metavar="DIR",
                        help="time on the benchmark's frames of the HDR images in DIR (default ../shared/data/hdr)")
    parser.add_argument("--clock", choices=("wall", "thread"), default="wall",
                        help="with --bench: wall time, or this thread's CPU time (steadier on a shared machine)")
    parser.add_argument("--default-malloc", action="store_true",
                        help="leave glibc's heap trimming as it is (by default the process keeps freed memory, as "
                             "svelive serve does)")
    args = parser.parse_args()
    cv2.setNumThreads(1)
    kept = False
    if not args.default_malloc:
        from svelive.memory import keep_freed_memory
        kept = keep_freed_memory()
    if args.bench is not None:
        bench_frames(args.bench, args.methods.split(","), args.repeats, args.clock,
                     "freed memory kept" if kept else "malloc's defaults")
        return
    raw, sensor = test_frame(args.pattern)
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, one thread; "
          f"pattern {args.pattern}, 1920x1200 12-bit, median of {args.repeats}; "
          f"load average {os.getloadavg()[0]:.1f} at start")
    for method in args.methods.split(","):
        repeats = 3 if method == "cubic" else args.repeats
        print(f"{method:20s} {time_method(raw, args.pattern, sensor, method, repeats):8.1f} ms", flush=True)
    if args.colour:
        pattern, cfa = COLOUR_LAYOUTS[args.layout]
        raw, sensor = test_frame(pattern, cfa=cfa)
        print(f"# colour: layout {args.layout} (pattern {pattern}, CFA {cfa}), 1920x1200 12-bit, "
              f"median of {args.repeats}")
        for method in args.colour_methods.split(","):
            for mode in ("joint", "split"):
                ms = time_method(raw, pattern, sensor, method, args.repeats, cfa=cfa, colour=mode)
                print(f"{mode + ' ' + method:20s} {ms:8.1f} ms", flush=True)


def bench_frames(data: str, methods: list[str], repeats: int, clock: str = "wall", malloc: str = "") -> None:
    """Median time (ms) of prepare + method on each benchmark timing frame; then median and worst per method.
    ``clock``: "wall" (perf_counter) or "thread" (this thread's CPU time, which other processes do not add to)."""
    from pathlib import Path

    from svelive.bench.runner import timing_frame
    from svelive.bench.scenes import (
        BENCH_SENSOR,
        NOISE_LEVELS,
        PATTERNS,
        Condition,
        default_data_dir,
        find_images,
        load_scene,
    )
    from svelive.reconstruction.input import prepare
    from svelive.reconstruction.single import run_method

    now = time.perf_counter if clock == "wall" else time.thread_time
    times: dict[str, list[float]] = {m: [] for m in methods}
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, one thread; bench frames "
          f"1920x1200, median of {repeats}, {clock} clock; load average {os.getloadavg()[0]:.1f} at start; "
          f"{malloc}")
    for path in find_images(Path(data) if data else default_data_dir()):
        scene = load_scene(path)
        for pattern in PATTERNS:
            for noise in NOISE_LEVELS:
                raw = timing_frame(scene, Condition(pattern, noise), 0)
                row = []
                for method in methods:
                    run = lambda: run_method(prepare(raw, pattern, BENCH_SENSOR), method)  # noqa: E731
                    run()
                    runs = []
                    for _ in range(repeats):
                        start = now()
                        run()
                        runs.append(now() - start)
                    times[method].append(float(np.median(runs)) * 1e3)
                    row.append(f"{method} {times[method][-1]:7.1f} ms")
                print(f"{path.stem:12s} {pattern:10s} {noise:6s} " + "  ".join(row), flush=True)
    for method, ms in times.items():
        print(f"{method:20s} median {np.median(ms):7.1f} ms, worst {max(ms):7.1f} ms over {len(ms)} frames")


if __name__ == "__main__":
    main()
