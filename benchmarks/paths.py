"""Which share of each frame's pixels takes which path of the default method, and what each path costs.

    python benchmarks/paths.py [--data ../shared/data/hdr] [--repeats 3]

On the benchmark's timing frames (svelive.bench: every HDR image of DIR under every
pattern, bright and 5 stops dim, resized to 1920x1200), one line per frame: the shares
of ``svelive.reconstruction.methods.adaptive.path_shares`` (censored pixels and the rows
holding them, pixels near 0 that step 4's polynomial takes, pixels that cannot tell their
level from 0 and the strips holding them, which the wide fallback visits; ``plain``: the
closed form alone), and the method's time split by path: the compiled pass of steps 1-4
(``fused``, which includes step 4 where it applies), the censored step, the wide fallback,
the lower-bound fill and the noise evidence, from this thread's CPU time in cProfile (one
thread; medians over ``--repeats``). The last lines are the medians over the frames.
"""

from __future__ import annotations

import argparse
import cProfile
import os
import platform
import pstats
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # this checkout

from svelive.bench.runner import timing_frame  # noqa: E402
from svelive.bench.scenes import BENCH_SENSOR, NOISE_LEVELS, PATTERNS, Condition, find_images, load_scene  # noqa: E402
from svelive.memory import keep_freed_memory  # noqa: E402
from svelive.reconstruction.input import prepare  # noqa: E402
from svelive.reconstruction.methods import adaptive  # noqa: E402

#: cProfile entries (function names in the adaptive package and base.py, cumulative time) that make up each path
PATHS = {"fused": ("fused_pass",), "censored": ("censored_pixels",), "wide": ("wide_fallback",),
         "lower": ("fill_lower_bounds",), "noise": ("noise_model",)}
SHARES = ("plain", "censored", "censored_rows", "near_zero", "wide", "wide_strips", "lower")


def path_times(inp, repeats: int) -> tuple[dict[str, float], float]:
    """Median ms per path (cumulative cProfile time of its entry functions) and of the whole method."""
    runs: dict[str, list[float]] = {name: [] for name in PATHS}
    totals = []
    for _ in range(repeats):
        profile = cProfile.Profile(time.thread_time)
        start = time.thread_time()
        profile.runcall(adaptive.run, inp)
        totals.append((time.thread_time() - start) * 1e3)
        stats = pstats.Stats(profile).stats
        for name, entries in PATHS.items():
            runs[name].append(1e3 * sum(cumulative for (_, _, function), (_, _, _, cumulative, _) in stats.items()
                                        if function in entries))
    return {name: float(np.median(ms)) for name, ms in runs.items()}, float(np.median(totals))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default="../shared/data/hdr", help="directory of HDR images (EXR)")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    cv2.setNumThreads(1)
    keep_freed_memory()
    print(f"# {platform.machine()}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}; bench frames 1920x1200, "
          f"one thread, CPU time, median of {args.repeats}")
    print(f"{'frame':34s} " + " ".join(f"{s:>8s}" for s in SHARES) + " |" + " ".join(f"{p:>8s}" for p in PATHS)
          + f" {'total':>7s}")
    rows = []
    for path in find_images(Path(args.data)):
        scene = load_scene(path)
        for pattern in PATTERNS:
            for noise in NOISE_LEVELS:
                inp = prepare(timing_frame(scene, Condition(pattern, noise), 0), pattern, BENCH_SENSOR)
                adaptive.run(inp)  # kernels loaded, buffers warm
                shares = adaptive.path_shares(inp)
                times, total = path_times(inp, args.repeats)
                rows.append((noise, shares, times, total))
                print(f"{path.stem + ' ' + pattern + ' ' + noise:34s} "
                      + " ".join(f"{100 * shares[s]:7.2f}%" for s in SHARES) + " |"
                      + " ".join(f"{times[p]:6.1f}ms" for p in PATHS) + f" {total:5.1f}ms", flush=True)
    for level in (None, *NOISE_LEVELS):
        chosen = [row for row in rows if level is None or row[0] == level]
        label = f"median over {len(chosen)} frames" + ("" if level is None else f" ({level})")
        print(f"{label:34s} " + " ".join(f"{100 * np.median([r[1][s] for r in chosen]):7.2f}%" for s in SHARES)
              + " |" + " ".join(f"{np.median([r[2][p] for r in chosen]):6.1f}ms" for p in PATHS)
              + f" {np.median([r[3] for r in chosen]):5.1f}ms")

if __name__ == "__main__":
    main()
