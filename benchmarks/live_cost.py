"""Per-frame cost of the live path on the demo camera's own frames, one thread.

    python benchmarks/live_cost.py [--size 1920x1200] [--frames 8] [--cfa none|RGGB]

Renders ``--frames`` frames of the demo scene (a still view, new noise in each)
and times ``svelive.Reconstructor`` on them: the default method alone, with
temporal fusion (what the service runs), and ``weighted`` with temporal fusion;
median over the frames after the first two (kernel loading): wall time, and the
thread's CPU time (everything runs on the caller's thread), which other
processes sharing the cores inflate far less. Run it on two checkouts in turn
(``git worktree``) to compare versions on one machine.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np

_HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or ".") != _HERE]
sys.path.insert(0, os.path.dirname(_HERE))  # this checkout, not an editable install's


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="1920x1200")
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--cfa", default="none")
    args = ap.parse_args()
    from svelive.capture.demo import DemoSource
    from svelive.reconstruction import Reconstructor
    try:  # what svelive serve does at start-up (absent from checkouts before it)
        from svelive.memory import keep_freed_memory
        keep_freed_memory()
    except ImportError:
        pass
    from svelive.reconstruction.single import methods

    width, height = (int(v) for v in args.size.lower().split("x"))
    demo = DemoSource("demo", width=width, height=height, fps=0, period_s=1e9, cfa=args.cfa)
    frames = list(demo.frames(limit=max(3, args.frames)))
    demo.close()
    camera = frames[0].camera
    print(f"# {platform.machine()}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}; demo {args.size} "
          f"cfa {args.cfa}, pattern {camera.pattern}, one thread", flush=True)
    for method, temporal in ((methods()[0], False), (methods()[0], True), ("weighted", True)):
        with Reconstructor(camera, method=method, temporal=temporal, workers=1) as stream:
            times, cpu = [], []
            for frame in frames:
                start, start_cpu = time.perf_counter(), time.thread_time()
                stream.process(frame)
                times.append(time.perf_counter() - start)
                cpu.append(time.thread_time() - start_cpu)
        print(f"{method:9s} temporal={temporal!s:5s} median {np.median(times[2:]) * 1e3:7.1f} ms, "
              f"CPU {np.median(cpu[2:]) * 1e3:7.1f} ms", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
