"""The band refresh (issue 25, svelive.reconstruction.settle): CPU per frame of a still 1920x1200 demo stream,
refresh off against ``refresh=K``.

    python benchmarks/settle_cost.py [--size 1920x1200] [--frames 30] [--refresh 2,4]

The streams take the same frames in turn, frame by frame, in one process (the machine's load then weighs on
both alike); each frame's thread CPU time (one thread). Prints the median over frames 9..N, the share of bands
the method ran on, the on-demand bands / cells / pixels per frame, and the outputs' RMS relative difference
against the stream with refresh off.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", default="1920x1200")
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--refresh", default="2,4")
    ap.add_argument("--sigmas", type=float, default=None, help="settle.UNSTABLE_SIGMAS")
    ap.add_argument("--cell", type=int, default=None, help="the on-demand atlas's cell (px), else settle.CELL")
    args = ap.parse_args()
    if args.sigmas:
        from svelive.reconstruction import settle
        settle.UNSTABLE_SIGMAS = args.sigmas
    if args.cell:
        from svelive.reconstruction import settle
        settle.CELL = args.cell
    from svelive.capture.demo import DemoSource
    from svelive.reconstruction import Reconstructor
    from svelive.memory import keep_freed_memory
    keep_freed_memory()
    width, height = (int(v) for v in args.size.lower().split("x"))
    demo = DemoSource("demo", width=width, height=height, fps=0, period_s=1e9, cfa="none")
    frames = list(demo.frames(limit=args.frames))
    demo.close()
    camera = frames[0].camera
    ks = [0] + [int(k) for k in args.refresh.split(",")]
    streams = {k: Reconstructor(camera, workers=1, refresh=k) for k in ks}
    cpu = {k: [] for k in ks}
    stats = {k: [] for k in ks}
    diff = {k: [] for k in ks}
    for i, frame in enumerate(frames):
        outs = {}
        for k in ks:
            t = time.thread_time()
            r = streams[k].process(frame)
            cpu[k].append(time.thread_time() - t)
            outs[k] = r.image
            stats[k].append(streams[k].last_partial or {})
        for k in ks:
            ref = outs[0]
            diff[k].append(float(np.sqrt(np.mean(((outs[k] - ref) / np.maximum(ref, 1.0)) ** 2))))
    print(f"# demo {args.size} mono, {args.frames} frames, load {os.getloadavg()[0]:.2f}; CPU ms per frame, "
          "median of frames 9..N (index 8..)")
    base = np.median(cpu[0][8:]) * 1e3
    for k in ks:
        c = np.median(cpu[k][8:]) * 1e3
        st = stats[k][8:]
        share = np.mean([s.get("computed", 0) / s["bands"] for s in st]) if k else 1.0
        line = f"refresh={k}: CPU {c:6.1f} ms (x{c / base:.2f})"
        if k:
            line += (f", bands computed {100 * share:.1f} %, on demand: bands {np.mean([s.get('demand_bands', 0) for s in st]):.2f}"
                     f" cells {np.mean([s.get('demand_cells', 0) for s in st]):.1f} px {np.mean([s.get('demand_px', 0) for s in st]):.1f}"
                     f" kept {np.mean([s.get('kept_px', 0) for s in st]):.0f} /frame, completed {sum(bool(s.get('completed')) for s in st)}; rel. RMS diff vs off "
                     f"{np.median(diff[k][8:]):.4f}")
        print(line, flush=True)
    print("per-frame CPU ms:", {k: [round(c * 1e3, 1) for c in cpu[k]] for k in ks})
    return 0


if __name__ == "__main__":
    sys.exit(main())
