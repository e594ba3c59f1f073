"""The ``svelive bench`` verb: speed against accuracy, stability sweeps, charts."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from svelive.atomic import write_bytes_atomic
from svelive.errors import SveliveError


def add_commands(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="benchmark every method: speed, accuracy, stability; charts",
                       description="Run every reconstruction method over real HDR images (simulated SVE frames, "
                                   "patterns 1,4/16,64 1,2/4,8 1/1/8/8, a bright and a dim scene) and the "
                                   "stability sweeps; write results.json, results.csv, speed_accuracy.png, "
                                   "stability.json, stability.png, adaptive_choice.png and summary.md to DIR.")
    p.add_argument("--quick", action="store_true", help="three images and fewer timing runs (a couple of minutes)")
    p.add_argument("-o", "--output", required=True, type=Path, metavar="DIR", help="directory for the results")
    p.add_argument("--data", type=Path, default=None, metavar="DIR",
                   help="directory of HDR .exr images (default: ../shared/data/hdr beside the checkout)")
    p.add_argument("--no-chart", action="store_true", help="skip the PNG charts (no matplotlib needed)")
    p.add_argument("--no-stability", action="store_true", help="skip the stability sweeps")
    p.set_defaults(func=cmd_bench)


def choice_map_example(pattern: str = "1,2/4,8"):
    """(truth, own-reading share, title) of the adaptive method on the shipped ``desk`` crop, bright, seed 0."""
    from svelive.bench.scenes import BENCH_SENSOR, Condition
    from svelive.reconstruction.methods.adaptive import own_share
    from svelive.reconstruction.input import prepare
    from svelive.simulate import load_sample_scene, simulate

    scene = load_sample_scene("desk")
    frame = simulate(Condition(pattern, "bright").radiance(scene), pattern, BENCH_SENSOR, seed=0)
    share = own_share(prepare(frame.raw, pattern, BENCH_SENSOR))
    return frame.truth, share, f"adaptive: per-pixel choice, shipped 'desk' crop, pattern {pattern}, bright"


def cmd_bench(args: argparse.Namespace) -> int:
    from svelive.bench import report
    from svelive.bench.runner import BenchConfig, quick_config, run_benchmark
    from svelive.bench.scenes import default_data_dir
    from svelive.bench.stability import run_stability

    out: Path = args.output
    if out.exists() and not out.is_dir():
        raise SveliveError(f"{out}: exists and is not a directory")
    if not args.no_chart:
        report._pyplot()  # fail before the long run, not after it
    out.mkdir(parents=True, exist_ok=True)
    config = quick_config() if args.quick else BenchConfig()
    start = time.perf_counter()
    results = run_benchmark(args.data or default_data_dir(), config)
    results["seconds"] = round(time.perf_counter() - start, 1)
    report.write_json(out / "results.json", results)
    report.write_csv(out / "results.csv", results["rows"])
    table = report.markdown_table(results["summary"])
    write_bytes_atomic(out / "summary.md", table.encode())
    if not args.no_chart:
        report.plot_speed_accuracy(results["summary"], out / "speed_accuracy.png", results["default_method"])
    if not args.no_chart:
        truth, share, title = choice_map_example()
        report.plot_choice_map(truth, share, out / "adaptive_choice.png", title)
    if not args.no_stability:
        sweeps = run_stability()
        report.write_json(out / "stability.json", sweeps)
        if not args.no_chart:
            report.plot_curves(sweeps, out / "stability.png")
    print(table, end="")
    print(f"wrote {out} in {time.perf_counter() - start:.0f} s")
    return 0
