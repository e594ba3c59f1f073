"""The ``svelive bench`` verb: speed against accuracy, stability sweeps, charts."""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from collections.abc import Callable
from pathlib import Path

from svelive.core.atomic import write_bytes_atomic
from svelive.core.errors import SveliveError


def add_commands(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="benchmark every method: speed, accuracy, stability; charts",
                       description="Run every reconstruction method over real HDR images (simulated SVE frames, "
                                   "patterns 1,4/16,64 1,2/4,8 1/1/8/8, a bright and a dim scene), the colour "
                                   "benchmark (joint against split, every colour layout, the RGB images) and the "
                                   "stability sweeps; write results.json, results.csv, speed_accuracy.png, "
                                   "colour.json, colour.csv, colour.png, colour.md, stability.json, stability.png, colour_edges.png, "
                                   "adaptive_choice.png, summary.md, the live chart (live.json, live.csv, live.md, "
                                   "live.png: each live ladder step's fps against PU21) and the default's guard "
                                   "grid (grid.json, grid.csv, "
                                   "grid.md, grid.png: every image x 4 patterns x 4 light levels x 2 true sensors x 6 "
                                   "noise models given, the default against aggregate and weighted) to DIR.")
    p.add_argument("--quick", action="store_true",
                   help="three images, the shipped crops for colour, fewer timing runs (a few minutes on two cores; each "
                        "part is announced as it starts)")
    p.add_argument("-o", "--output", required=True, type=Path, metavar="DIR", help="directory for the results")
    p.add_argument("--data", type=Path, default=None, metavar="DIR",
                   help="directory of HDR .exr images (default: ../shared/data/hdr beside the checkout)")
    p.add_argument("--no-chart", action="store_true", help="skip the PNG charts (no matplotlib needed)")
    p.add_argument("--no-stability", action="store_true", help="skip the stability sweeps")
    p.add_argument("--no-mono", action="store_true", help="skip the monochrome speed/accuracy run")
    p.add_argument("--no-colour", action="store_true", help="skip the colour benchmark")
    p.add_argument("--no-live", action="store_true",
                   help="skip the live chart (every live ladder step: fps on this machine against PU21; live.png)")
    p.add_argument("--no-grid", action="store_true",
                   help="skip the default's guard grid (with --quick: the issue's sensor only)")
    p.set_defaults(func=cmd_bench)


def choice_map_example(pattern: str = "1,2/4,8"):
    """(truth, own-reading share, title) of the adaptive method on the shipped ``desk`` crop, bright, seed 0."""
    from svelive.bench.scenes import BENCH_SENSOR, Condition
    from svelive.reconstruction.input import prepare
    from svelive.reconstruction.methods.adaptive import own_share
    from svelive.simulation import load_sample_scene, simulate

    scene = load_sample_scene("desk")
    frame = simulate(Condition(pattern, "bright").radiance(scene), pattern, BENCH_SENSOR, seed=0)
    share = own_share(prepare(frame.raw, pattern, BENCH_SENSOR))
    return frame.truth, share, f"adaptive: per-pixel choice, shipped 'desk' crop, pattern {pattern}, bright"


def run_colour(out: Path, data: Path, quick: bool, images: tuple[str, ...], chart: bool) -> str:
    """The colour benchmark (the shipped crops when ``quick``, else the RGB images of ``data``); its Markdown."""
    from svelive.bench import colour, report

    start = time.perf_counter()
    if quick:
        scenes, skipped = colour.shipped_scenes(), {}
        config = colour.quick_colour_config()
    else:
        scenes, skipped = colour.data_scenes(data, images)
        config = colour.ColourBenchConfig(images=images)
    results = colour.run_colour_benchmark(scenes, config, skipped=skipped)
    results["seconds"] = round(time.perf_counter() - start, 1)
    results["source"] = "shipped 256x256 crops" if quick else str(data)
    report.write_json(out / "colour.json", results)
    report.write_csv(out / "colour.csv", results["rows"])
    table = colour.markdown_colour(results)
    write_bytes_atomic(out / "colour.md", table.encode())
    if chart:
        report.plot_colour(results, out / "colour.png")
    return "\n" + table


def run_live(out: Path, data: Path, quick: bool, images: tuple[str, ...], chart: bool) -> str:
    """The live chart (svelive.bench.live; the shipped crops and smaller frames when ``quick``); its Markdown."""
    from svelive.bench import live, report

    start = time.perf_counter()
    mono, colour, source = live.live_scenes(None if quick else data, images)
    results = live.run_live_benchmark(mono, colour, live.quick_live_config() if quick else live.LiveBenchConfig(),
                                      log=lambda line: print(line, file=sys.stderr, flush=True))
    results["seconds"] = round(time.perf_counter() - start, 1)
    results["source"] = source
    report.write_json(out / "live.json", results)
    report.write_csv(out / "live.csv", live.csv_rows(results))
    table = live.markdown_live(results)
    write_bytes_atomic(out / "live.md", table.encode())
    if chart:
        report.plot_live(results, out / "live.png")
    return "\n" + table


def run_grid(out: Path, data: Path, quick: bool, images: tuple[str, ...], chart: bool) -> str:
    """The default's guard grid over the images of ``data`` (``images`` only, if given); its Markdown."""
    from svelive.bench import report
    from svelive.bench.scenes import find_images, load_scene
    from svelive.bench.stability import GridConfig, markdown_grid, quick_grid_config
    from svelive.bench.stability import run_grid as grid

    wanted = {name.lower() for name in images}
    paths = [p for p in find_images(data) if not wanted or p.stem.lower() in wanted]
    if not paths:
        raise SveliveError(f"{data}: holds none of the images {', '.join(images)}")
    start = time.perf_counter()
    results = grid({p.stem: load_scene(p) for p in paths}, quick_grid_config() if quick else GridConfig(),
                   log=lambda line: print(line, file=sys.stderr, flush=True))
    results["seconds"] = round(time.perf_counter() - start, 1)
    results["source"] = str(data)
    report.write_json(out / "grid.json", results)
    report.write_csv(out / "grid.csv", results["rows"])
    table = markdown_grid(results["summary"])
    write_bytes_atomic(out / "grid.md", table.encode())
    if chart:
        report.plot_grid(results, out / "grid.png")
    return "\n" + table


def part_announcer(args: argparse.Namespace, start: float) -> Callable[[str], None]:
    """A function that says on stderr which part of the benchmark starts (``[2/5] NAME``, the time so far)."""
    total = sum(not getattr(args, flag) for flag in ("no_mono", "no_live", "no_colour", "no_grid", "no_stability"))
    numbers = itertools.count(1)

    def say(name: str) -> None:
        print(f"svelive bench: [{next(numbers)}/{total}] {name} ({time.perf_counter() - start:.0f} s so far)",
              file=sys.stderr, flush=True)

    return say


def cmd_bench(args: argparse.Namespace) -> int:
    from svelive.bench import report
    from svelive.bench.runner import BenchConfig, quick_config, run_benchmark
    from svelive.bench.scenes import default_data_dir, find_images, shipped_data_dir
    from svelive.bench.stability import colour_edge_crops, run_stability

    out: Path = args.output
    if out.exists() and not out.is_dir():
        raise SveliveError(f"{out}: exists and is not a directory")
    if not args.no_chart:
        report._pyplot()  # fail before the long run, not after it
    if not args.no_colour:
        from svelive.metrics import skimage_color

        skimage_color()  # the colour error's library, checked before the long run too
    config = quick_config() if args.quick else BenchConfig()
    data = args.data or default_data_dir()
    if args.data is None and not data.is_dir():
        data = shipped_data_dir()
        print(f"svelive bench: {default_data_dir()} not found: benchmarking the shipped crops in {data} "
              "(pass --data DIR for the full images)", file=sys.stderr)
    find_images(data)  # a missing or empty directory is said before any part starts
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    table = ""
    say = part_announcer(args, start)
    if not args.no_mono:
        say("speed and accuracy of every method (monochrome)")
        results = run_benchmark(data, config)
        results["seconds"] = round(time.perf_counter() - start, 1)
        report.write_json(out / "results.json", results)
        report.write_csv(out / "results.csv", results["rows"])
        table = report.markdown_table(results["summary"])
        write_bytes_atomic(out / "summary.md", table.encode())
        if not args.no_chart:
            report.plot_speed_accuracy(results["summary"], out / "speed_accuracy.png", results["default_method"])
            truth, share, title = choice_map_example()
            report.plot_choice_map(truth, share, out / "adaptive_choice.png", title)
    if not args.no_live:
        say("the live chart (every live ladder step's fps against PU21)")
        table += run_live(out, data, args.quick, config.images, not args.no_chart)
    if not args.no_colour:
        say("colour: joint against split on every layout")
        table += run_colour(out, data, args.quick, config.images, not args.no_chart)
    if not args.no_grid:
        say("the default's guard grid")
        table += run_grid(out, data, args.quick, config.images, not args.no_chart)
    if not args.no_stability:
        say("stability sweeps")
        sweeps = run_stability(colour=not args.no_colour)
        report.write_json(out / "stability.json", sweeps)
        if not args.no_chart:
            report.plot_curves(sweeps, out / "stability.png")
            if not args.no_colour:
                report.plot_colour_edges(colour_edge_crops(), out / "colour_edges.png")
    print(table, end="")
    print(f"wrote {out} in {time.perf_counter() - start:.0f} s")
    return 0
