"""Parallel efficiency of the live path (issue 25.2: >= 1.8x on 2 threads): wall time per frame of the
service's stream (default method, temporal fusion, the band refresh) on one thread against two.

    python benchmarks/parallel.py [--size 1920x1200] [--frames 30] [--cfa none|RGGB] [--refresh K]

Three streams take the same demo frames (a still view, new noise in each) in turn, frame by frame, in one
process, so the machine's load weighs on all alike:
- ``1 thread``: ``Reconstructor(workers=1)``, everything on the caller's thread;
- ``2 threads``: ``workers=2``, each frame's strips spread over two threads (the service's default);
- ``2 threads, ahead``: ``workers=2``, and the next frame's ``estimate`` on a second caller thread while this
  frame is fused (the service's ``--parallel-frames 2``).
Prints each stream's median wall time per frame over frames 9..N (noise model trusted, refresh running),
its CPU time per frame (the process's, all threads) and the efficiency: 1-thread wall / this wall. The
ahead stream's wall time is its throughput: the time between two fused frames.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="1920x1200")
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--cfa", default="none")
    ap.add_argument("--refresh", type=int, default=None, help="the band refresh's K (default: the service's)")
    args = ap.parse_args()
    if args.frames < 12:
        ap.error("--frames must be at least 12 (the median is over frames 9..N)")
    from svelive.capture.demo import DemoSource
    from svelive.memory import keep_freed_memory
    from svelive.reconstruction import Reconstructor
    from svelive.reconstruction.live import LIVE_REFRESH

    keep_freed_memory()
    refresh = LIVE_REFRESH if args.refresh is None else args.refresh
    width, height = (int(v) for v in args.size.lower().split("x"))
    demo = DemoSource("demo", width=width, height=height, fps=0, period_s=1e9, cfa=args.cfa)
    frames = list(demo.frames(limit=args.frames))
    demo.close()
    camera = frames[0].camera
    print(f"# {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}; demo {args.size} cfa {args.cfa}, "
          f"{args.frames} frames, refresh {refresh}; medians of frames 9..N", flush=True)

    names = ("1 thread", "2 threads", "2 threads, ahead")
    streams = [Reconstructor(camera, workers=w, refresh=refresh) for w in (1, 2, 2)]
    wall = {name: [] for name in names}
    cpu = {name: [] for name in names}
    ahead = ThreadPoolExecutor(max_workers=1)
    pending = ahead.submit(streams[2].estimate, frames[0])
    try:
        for i, frame in enumerate(frames):
            for name, stream in zip(names[:2], streams[:2]):
                start, start_cpu = time.perf_counter(), time.process_time()
                stream.process(frame)
                wall[name].append(time.perf_counter() - start)
                cpu[name].append(time.process_time() - start_cpu)
            start, start_cpu = time.perf_counter(), time.process_time()
            estimated = pending.result()
            if i + 1 < len(frames):
                pending = ahead.submit(streams[2].estimate, frames[i + 1])
            streams[2].fuse(estimated)
            if i + 1 < len(frames):  # the next estimate's remaining time belongs to the next frame's interval
                pending.result()
            wall[names[2]].append(time.perf_counter() - start)
            cpu[names[2]].append(time.process_time() - start_cpu)
            print(f"frame {i + 1}/{len(frames)}: " + ", ".join(f"{n} {wall[n][-1] * 1e3:.0f} ms" for n in names),
                  file=sys.stderr, flush=True)
    finally:
        ahead.shutdown()
        for stream in streams:
            stream.close()
    base = float(np.median(wall[names[0]][8:]))
    for name in names:
        w, c = float(np.median(wall[name][8:])), float(np.median(cpu[name][8:]))
        print(f"{name:17s} wall {w * 1e3:6.1f} ms, CPU {c * 1e3:6.1f} ms a frame, efficiency x{base / w:.2f}",
              flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
