"""CPU cost of the directional demosaicing stage (svelive.reconstruction.colour.directional) on the demo camera's
colour frame, one thread.

    python benchmarks/directional_cost.py [--size 1920x1200] [--repeats 9] [--compare OLD/directional.py]

Renders one frame of the demo scene through an RGGB dual-ISO mosaic, runs ``colour.joint`` once, then times
the stage alone on copies of its output (``directional_channels``) and ``joint`` without and with
``directional=True``, alternated: this thread's CPU time, median over ``--repeats`` runs after a warm-up.
``--compare`` loads another version of directional.py (a file from an older checkout, e.g. written by
``git show REV:svelive/reconstruction/colour/directional.py``) and times its stage alternated with this one's
in the same process, and says whether the two give the same bits: on a shared machine only such ratios are
worth comparing.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import shutil
import sys
import tempfile
import time
from types import ModuleType
from typing import Callable

import numpy as np

_HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or ".") != _HERE]
sys.path.insert(0, os.path.dirname(_HERE))  # this checkout, not an editable install's


def cpu_ms(run: Callable[[], object]) -> float:
    """This thread's CPU time of ``run()``, ms."""
    start = time.thread_time()
    run()
    return (time.thread_time() - start) * 1e3


def load_copy(path: str, directory: str) -> ModuleType:
    """The module of the file ``path`` imported from a copy in ``directory`` under a name of its own: its kernels
    compile afresh (numba's disk cache keys on the file's path, and a module imported by path cannot be found
    again by name when a later run loads its cached machine code)."""
    copy = os.path.join(directory, "directional_compared.py")
    shutil.copyfile(path, copy)
    spec = importlib.util.spec_from_file_location("directional_compared", copy)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="1920x1200")
    ap.add_argument("--repeats", type=int, default=9)
    ap.add_argument("--compare", help="another version's directional.py, timed alternated with this one's")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as scratch:
        return measure(args, scratch)


def measure(args: argparse.Namespace, scratch: str) -> int:
    """The timings (module docstring); ``scratch``: a directory for the compared version's copy."""
    import cv2

    from svelive.capture.demo import DemoSource
    from svelive.memory import keep_freed_memory
    from svelive.reconstruction.colour import directional, joint
    from svelive.reconstruction.input import prepare
    from svelive.reconstruction.methods import METHODS

    cv2.setNumThreads(1)
    keep_freed_memory()
    width, height = (int(v) for v in args.size.lower().split("x"))
    demo = DemoSource("demo", width=width, height=height, fps=0, period_s=1e9, cfa="RGGB")
    frame = next(iter(demo.frames(limit=1)))
    demo.close()
    inp, spec = prepare(frame.raw, frame.camera), METHODS["adaptive"]
    base = joint(inp, spec)
    image, luminance = base.estimate.image, base.estimate.luminance
    share, floor = base.chroma.layout.share, directional.log_floor(inp, base.chroma.layout)
    versions = {"this": directional}
    if args.compare:
        versions["compared"] = load_copy(args.compare, scratch)
    print(f"# {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}; demo {args.size} RGGB, one thread, CPU, "
          f"median of {args.repeats} after a warm-up", flush=True)
    times: dict[str, list[float]] = {name: [] for name in versions}
    outputs = {}
    for _ in range(args.repeats + 1):
        for name, module in versions.items():
            out_image, out_luminance = image.copy(), luminance.copy()
            times[name].append(cpu_ms(lambda: module.directional_channels(inp, out_luminance, out_image, share, floor)))
            outputs[name] = (out_image, out_luminance)
    for name, values in times.items():
        print(f"stage ({name}) {np.median(values[1:]):7.1f} ms", flush=True)
    if args.compare:
        same = all(np.array_equal(a, b) for a, b in zip(outputs["this"], outputs["compared"]))
        print(f"same bits: {same}")
    plain, with_stage = [], []
    for _ in range(args.repeats + 1):
        plain.append(cpu_ms(lambda: joint(inp, spec)))
        with_stage.append(cpu_ms(lambda: joint(inp, spec, directional=True)))
    print(f"joint {np.median(plain[1:]):7.1f} ms, with directional=True {np.median(with_stage[1:]):7.1f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
