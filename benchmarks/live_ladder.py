"""Speed and accuracy of every live ladder step (svelive.reconstruction.live.LADDER), mono and colour.

    python benchmarks/live_ladder.py [--data DIR] [--quick] [--workers 2] [--json out.json] [--chart out.png]

What ``svelive bench`` charts as live.png (svelive.bench.live), as a table with
the machine and its load: for each step, ``svelive.Reconstructor(camera,
method=..., temporal=..., workers=2)`` on 1920x1200 12-bit frames of a still
scene (the first bench image resized, new noise in each frame; median wall and
process CPU time per frame after 3 warm-up frames, bright and dim) and its
PU21-PSNR after 8 frames of a static scene on every bench image at its own size
(bright and dim), monochrome (patterns 1,4/16,64, 1,2/4,8, 1/1/8/8) and colour
(dual-ISO RGGB). ``--data`` defaults to ../shared/data/hdr beside the checkout,
else the shipped crops in svelive/data; ``--quick``: the shipped crops, 960x600
frames, one monochrome pattern (under a minute).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

_HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or ".") != _HERE]
sys.path.insert(0, os.path.dirname(_HERE))  # this checkout, not an editable install's

from svelive.bench import live  # noqa: E402
from svelive.bench.scenes import default_data_dir  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=None,
                    help="directory of HDR .exr images (default ../shared/data/hdr, else the shipped crops)")
    ap.add_argument("--quick", action="store_true", help="the shipped crops, 960x600 frames, one mono pattern")
    ap.add_argument("--workers", type=int, default=2, help="the stream's threads per frame (default 2)")
    ap.add_argument("--timed-images", type=int, default=1, help="how many images (the first ones) are timed")
    ap.add_argument("--json", type=Path, help="also write the results as JSON")
    ap.add_argument("--chart", type=Path, help="also draw the chart (PNG, needs matplotlib)")
    args = ap.parse_args()
    from dataclasses import replace

    from svelive.bench import report
    from svelive.bench.runner import machine

    data = args.data or default_data_dir()
    if not args.quick and not data.is_dir():
        print(f"# {data} not found: the shipped crops in svelive/data", file=sys.stderr)
    use = None if args.quick or not data.is_dir() else data
    config = live.quick_live_config() if args.quick else live.LiveBenchConfig()
    config = replace(config, workers=args.workers, timed_images=args.timed_images)
    info = machine()
    print(f"# {info['cpu']}, {info['cores']} cores, {info['system']}; python {info['python']}, numpy "
          f"{info['numpy']}, opencv {info['opencv']}; load {_load()} at start", flush=True)
    start = time.perf_counter()
    mono, colour, source = live.live_scenes(use)
    print(f"# scenes: {source} (mono {', '.join(mono)}; colour {', '.join(colour)}); frames "
          f"{config.timing_size[1]}x{config.timing_size[0]}, {config.workers} workers", flush=True)
    results = live.run_live_benchmark(mono, colour, config, log=lambda line: print("#", line, flush=True))
    results["seconds"] = round(time.perf_counter() - start, 1)
    results["source"] = source
    print(live.markdown_live(results), end="")
    print(f"# {results['seconds']:.0f} s; load {_load()} at end", flush=True)
    if args.json:
        report.write_json(args.json, results)
    if args.chart:
        report.plot_live(results, args.chart)
    return 0


def _load() -> str:
    return " / ".join(f"{v:.2f}" for v in os.getloadavg()) if hasattr(os, "getloadavg") else "unknown"


if __name__ == "__main__":
    sys.exit(main())
