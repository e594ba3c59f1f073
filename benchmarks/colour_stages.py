"""Where a colour frame's time goes, stage by stage: the live path on the demo camera's colour frame, one thread.

    python benchmarks/colour_stages.py [--size 1920x1200] [--frames 12] [--cfa RGGB] [--baseline REV]

Renders ``--frames`` frames of the demo scene (a still view, new noise in each; dual-ISO 1/1/8/8 on
the colour filter) and runs ``svelive.Reconstructor`` (the default method, ``workers=1``) on them, single
frame and with temporal fusion, with each stage of the colour path wrapped in a timer of the thread's CPU
time (``time.thread_time``; everything runs on the caller's thread). Prints, per stage, the median over
the frames after the first two (kernel loading) of its time in a frame, inclusive of the stages indented
under it (``method`` is the monochrome method on the folded luminance; ``other`` lines are what the stages
listed do not cover). The wrappers add about a microsecond a call.

``--baseline REV``: also the same stages of git revision REV of this repository (its ``svelive`` package
extracted to a temporary directory), ``--rounds`` processes of each version alternated on the same saved
frames, each frame's times pooled; then the ratio of each stage's medians (this checkout / baseline).
Each version runs in processes of its own: two copies of one version in one process differed by up to
1.35x on the fusion's stage, whichever came second (where their frame-sized arrays landed in the heap).
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import pickle
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from dataclasses import replace
from typing import Callable

import numpy as np

_HERE = os.path.dirname(os.path.abspath(__file__))
_ROOT = os.path.dirname(_HERE)
sys.path[:] = [p for p in sys.path if os.path.abspath(p or ".") != _HERE]
sys.path.insert(0, _ROOT)  # this checkout, not an editable install's

#: (label, module under the package, attribute): what is timed, in the order printed. A label's dots
#: say which stage it runs inside (for the "other" lines).
STAGES: tuple[tuple[str, str, str], ...] = (
    ("prepare", "reconstruction.stream", "prepare"),
    ("joint", "reconstruction.colour", "joint"),
    ("joint.chroma", "reconstruction.colour.joint_parts", "chroma"),
    ("joint.chroma.cell_stats", "reconstruction.colour.shares", "_cell_stats"),
    ("joint.chroma.smooth_cells", "reconstruction.colour.shares", "_smooth_cells"),
    ("joint.chroma.cell_pass", "reconstruction.colour.shares", "_cell_pass"),  # the two in one (chroma89)
    ("joint.chroma.white_balance", "reconstruction.colour.shares", "white_balance"),
    ("joint.chroma.cell_values", "reconstruction.colour.shares", "_cell_values"),
    ("joint.chroma.centred", "reconstruction.colour.shares", "_centred"),
    ("joint.chroma.shares", "reconstruction.colour.shares", "_shares"),
    ("joint.chroma.blend", "reconstruction.colour.shares", "_blend"),
    ("joint.chroma.shrink", "reconstruction.colour.shares", "_shrink"),
    ("joint.chroma.normalise", "reconstruction.colour.shares", "_normalise"),
    ("joint.chroma.share_pass", "reconstruction.colour.shares", "_share_pass"),  # cell_values .. normalise in one
    ("joint.chroma.chroma_pass", "reconstruction.colour.shares", "_chroma_pass"),  # a given white: all in one
    ("joint.interpolation", "reconstruction.colour.joint_parts", "interpolation"),
    ("joint.fold", "reconstruction.colour.joint_parts", "luminance_input"),
    ("joint.method", "", ""),  # the method's run, wrapped through the stream's method_spec
    ("joint.refine", "reconstruction.colour.joint_parts", "refine"),
    ("estimate_variance", "reconstruction.stream", "estimate_variance"),
    ("window_estimate", "reconstruction.stream", "window_estimate"),
    ("own_reading_scales", "reconstruction.stream", "own_reading_scales"),
    ("share_error", "reconstruction.stream", "share_error"),  # (the plane; the stream's fusion reads it by cell:)
    ("share_error_cells", "reconstruction.stream", "share_error_cells"),
    ("fuse", "reconstruction.stream", "fuse"),
    ("fuse_chroma", "reconstruction.stream", "fuse_chroma"),
    ("luminance_noise", "reconstruction.stream", "luminance_noise"),
    ("refined", "reconstruction.stream", "_refined"),
    ("refined.interpolation", "reconstruction.colour", "interpolation"),
    ("refined.refine", "reconstruction.colour", "refine"),  # (and colourise, since they share a pass)
    ("colourise", "reconstruction.colour", "colourise"),
    ("lattice", "reconstruction.colour", "lattice_channels"),
)


class Timers:
    """Thread-CPU time per stage label, summed over a frame (ms), with the frames' totals kept in lists."""

    def __init__(self) -> None:
        self.frame: dict[str, float] = defaultdict(float)
        self.frames: dict[str, list[float]] = defaultdict(list)

    def wrap(self, label: str, function: Callable) -> Callable:
        """``function`` with its thread-CPU time added to ``label``'s."""
        def timed(*args, **kwargs):
            start = time.thread_time()
            try:
                return function(*args, **kwargs)
            finally:
                self.frame[label] += (time.thread_time() - start) * 1e3
        timed.__wrapped__ = function
        return timed

    def end_frame(self, total_ms: float) -> None:
        """Close a frame: every label's time in it (0 where it did not run) and its total."""
        for label, *_ in STAGES:
            self.frames[label].append(self.frame.get(label, 0.0))
        self.frames["total"].append(total_ms)
        self.frame.clear()


def instrument(package: str, timers: Timers) -> None:
    """Wrap the stages of ``package`` in ``timers``' timers (for this process)."""
    for label, module, attribute in STAGES:
        if not module:
            continue
        mod = importlib.import_module(f"{package}.{module}")
        if hasattr(mod, attribute):
            setattr(mod, attribute, timers.wrap(label, getattr(mod, attribute)))
    stream = importlib.import_module(f"{package}.reconstruction.stream")
    spec_of = stream.method_spec

    def method_spec(name: str):
        spec = spec_of(name)
        return replace(spec, run=timers.wrap("joint.method", spec.run))
    stream.method_spec = method_spec


def render(size: tuple[int, int], count: int, cfa: str) -> tuple[list[np.ndarray], object]:
    """``count`` raw frames of this checkout's demo camera, uint16 (H, W) each, and the camera (svelive.Camera)."""
    from svelive.capture.demo import DemoSource
    demo = DemoSource("demo", width=size[0], height=size[1], fps=0, period_s=1e9, cfa=cfa)
    frames = list(demo.frames(limit=count))
    demo.close()
    return [frame.raw for frame in frames], frames[0].camera


def table(rows: dict[str, dict[str, list[float]]], skip: int) -> list[str]:
    """The stage table's lines: per stage the median of each run's frame times (ms), ``other`` lines under
    stages with timed parts, and the ratio to the first run where there are two."""
    names = list(rows)
    header = "| stage | " + " | ".join(names) + (" | ratio |" if len(names) == 2 else " |")
    lines = [header, "|" + " --- |" * (len(names) + 1 + (len(names) == 2))]
    labels = [label for label, *_ in STAGES]

    def median(name: str, label: str) -> float:
        return float(np.median(rows[name][label][skip:]))

    def line(title: str, values: list[float]) -> str:
        ratio = f" | {values[1] / values[0]:.2f}" if len(values) == 2 and values[0] > 0.05 else (
            " | " if len(values) == 2 else "")
        return f"| {title} | " + " | ".join(f"{v:.1f}" for v in values) + ratio + " |"

    for label in labels:
        values = [median(name, label) for name in names]
        if max(values) < 0.05:
            continue
        depth = label.count(".")
        lines.append(line("&nbsp;" * 4 * depth + label.split(".")[-1], values))
        children = [c for c in labels if c.startswith(label + ".") and c.count(".") == depth + 1]
        last_child = children[-1] if children else None
        if last_child is not None:
            other = [float(np.median(np.array(rows[name][label][skip:])
                                     - np.sum([rows[name][c][skip:] for c in children], axis=0))) for name in names]
            lines.append(line("&nbsp;" * 4 * (depth + 1) + "other", other))
    totals = [median(name, "total") for name in names]
    top = [c for c in labels if "." not in c]
    other = [float(np.median(np.array(rows[name]["total"][skip:])
                             - np.sum([rows[name][c][skip:] for c in top], axis=0))) for name in names]
    lines.append(line("other", other))
    lines.append(line("**total**", totals))
    return lines


def measure(root: str, data: str, temporal: bool) -> dict[str, list[float]]:
    """Per-frame stage times (ms) of the checkout at ``root`` on the frames saved in ``data`` (run in a
    process of its own: ``--worker``)."""
    sys.path.insert(0, root)
    from svelive.memory import keep_freed_memory
    from svelive.reconstruction import Reconstructor
    keep_freed_memory()  # what svelive serve does at start-up
    timers = Timers()
    instrument("svelive", timers)
    with open(os.path.join(data, "camera.pickle"), "rb") as f:
        camera = pickle.load(f)
    raws = np.load(os.path.join(data, "frames.npy"))
    with Reconstructor(camera, temporal=temporal, workers=1) as stream:
        for raw in raws:
            start = time.thread_time()
            stream.process(raw)
            timers.end_frame((time.thread_time() - start) * 1e3)
    return dict(timers.frames)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="1920x1200")
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--cfa", default="RGGB")
    ap.add_argument("--baseline", default=None, help="a git revision to compare with")
    ap.add_argument("--rounds", type=int, default=3, help="processes of each version, alternated")
    ap.add_argument("--worker", nargs=3, metavar=("ROOT", "DATA", "TEMPORAL"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        root, data, temporal = args.worker
        print(json.dumps(measure(root, data, temporal == "1")))
        return 0
    import platform
    size = tuple(int(v) for v in args.size.lower().split("x"))
    count = max(3, args.frames)
    with tempfile.TemporaryDirectory() as where:
        raws, camera = render(size, count, args.cfa)  # one set of frames for every process
        np.save(os.path.join(where, "frames.npy"), np.stack(raws))
        with open(os.path.join(where, "camera.pickle"), "wb") as f:
            pickle.dump(camera, f)
        roots = {"this checkout": _ROOT}
        if args.baseline:
            base = os.path.join(where, "baseline")
            os.mkdir(base)
            archive = subprocess.run(["git", "-C", _ROOT, "archive", args.baseline, "svelive"], check=True,
                                     capture_output=True).stdout
            subprocess.run(["tar", "-x", "-C", base], input=archive, check=True)
            roots = {f"baseline {args.baseline}": base, **roots}
        rounds = args.rounds if args.baseline else 1
        print(f"# {platform.machine()}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}; demo {args.size} "
              f"cfa {args.cfa}, one thread, thread CPU ms a frame, median of frames 3-{count} of {rounds} "
              f"process(es) each" + (", the versions' processes alternated" if args.baseline else ""), flush=True)
        for temporal in (False, True):
            pooled: dict[str, dict[str, list[float]]] = {name: defaultdict(list) for name in roots}
            for index in range(rounds):
                for name in (list(roots) if index % 2 == 0 else list(roots)[::-1]):
                    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
                    out = subprocess.run([sys.executable, os.path.abspath(__file__), "--worker", roots[name], where,
                                          "1" if temporal else "0"], check=True, capture_output=True, text=True,
                                         env=env).stdout
                    for label, values in json.loads(out.splitlines()[-1]).items():
                        pooled[name][label].extend(values[2:])  # after kernel loading
            print(f"\n## {'with temporal fusion' if temporal else 'single frame'}\n")
            print("\n".join(table(pooled, 0)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
