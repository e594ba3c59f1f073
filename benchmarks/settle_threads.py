"""The band refresh on two threads (issue 25, item 2): how a still 1920x1200 monochrome demo stream's CPU a frame
splits between the thread that calls ``Reconstructor.process`` and the stream's pool.

    python benchmarks/settle_threads.py [--size 1920x1200] [--frames 36] [--refresh 8] [--workers 2]
                                        [--code DIR] [--rounds 1]

Per frame (frames 11..N, after the noise model is trusted and the bands settle): wall time, the process's CPU
time (every thread), the calling thread's CPU time; the pool's is the difference. The calling thread's CPU
bounds the wall time a frame from below however idle the cores are, so it is the figure to compare on a shared
machine, with the process's (the work done). ``--code DIR``: import svelive from that checkout (another branch's,
to compare two in turn on the same machine), else this one's. The frames are rendered once and the stream
takes them ``--rounds`` times.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", default="1920x1200")
    ap.add_argument("--frames", type=int, default=36)
    ap.add_argument("--refresh", type=int, default=8)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=1)
    ap.add_argument("--code", default=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    args = ap.parse_args()
    sys.path.insert(0, os.path.abspath(args.code))
    from svelive.capture.demo import DemoSource
    from svelive.memory import keep_freed_memory
    from svelive.reconstruction import Reconstructor

    keep_freed_memory()
    width, height = (int(v) for v in args.size.lower().split("x"))
    demo = DemoSource("demo", width=width, height=height, fps=0, period_s=1e9, cfa="none")
    frames = list(demo.frames(limit=args.frames))
    demo.close()
    rows = []
    with Reconstructor(frames[0].camera, workers=args.workers, refresh=args.refresh) as stream:
        for _ in range(args.rounds):
            for i, frame in enumerate(frames):
                wall, cpu, caller = time.perf_counter(), time.process_time(), time.thread_time()
                stream.process(frame)
                if i >= 10:
                    rows.append((time.perf_counter() - wall, time.process_time() - cpu, time.thread_time() - caller))
    wall, cpu, caller = (np.median(column) * 1e3 for column in np.array(rows).T)
    pool = np.median([c - t for _, c, t in rows]) * 1e3
    print(f"# {args.code}: demo {args.size} mono, refresh {args.refresh}, workers {args.workers}, {len(rows)} frames "
          f"measured, load {os.getloadavg()[0]:.2f}; medians a frame")
    print(f"wall {wall:.1f} ms, process CPU {cpu:.1f} ms, calling thread CPU {caller:.1f} ms, pool CPU {pool:.1f} ms")
    return 0


if __name__ == "__main__":
    sys.exit(main())
