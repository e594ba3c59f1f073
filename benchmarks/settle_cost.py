"""The band refresh (issue 25, svelive.reconstruction.settle): CPU per frame of a still 1920x1200 demo stream,
refresh off against ``refresh=K``.

    python benchmarks/settle_cost.py [--size 1920x1200] [--frames 30] [--refresh 2,4] [--pattern 1/1/8/8]
                                     [--bench dim [--image Bonita.exr]]

The streams take the same frames in turn, frame by frame, in one process (the machine's load then weighs on
both alike); each frame's thread CPU time (one thread). Prints the median over frames 9..N, the share of bands
the method ran on, the frames that ran every band, the on-demand bands / cells / pixels per frame, and the
outputs' RMS relative difference against the stream with refresh off, and a SHA-256 of each stream's output
images, motion masks and history weights over every frame (two checkouts' streams compared bit for bit).

``--bench NOISE``: ``svelive bench --live``'s timed frames instead of the demo's: ``--image`` (an HDR image; by
default ../shared/data/hdr/Bonita.exr, else svelive's shipped cannon crop) resized to ``--size`` under the
bench's sensor, ``--pattern`` (default 1,4/16,64) and noise level (bright, or dim: 5 stops under), new noise in
each frame; then also the mean PU21-PSNR (dB) of frames 9..N against the simulator's truth.
"""

from __future__ import annotations

import argparse
import hashlib
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
    ap.add_argument("--pattern", default=None, help="the exposure pattern (the demo's, or 1,4/16,64 with --bench)")
    ap.add_argument("--bench", choices=("bright", "dim"), default=None,
                    help="svelive bench --live's frames of --image at this noise level instead of the demo's")
    ap.add_argument("--image", default=None, help="with --bench: an HDR image (default: Bonita, else cannon)")
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
    from svelive.metrics import pu21_psnr
    keep_freed_memory()
    width, height = (int(v) for v in args.size.lower().split("x"))
    truth = None
    if args.bench:
        frames, camera, truth, source = bench_frames(args.image, args.pattern or "1,4/16,64", args.bench,
                                                     (height, width), args.frames)
    else:
        options = {} if args.pattern is None else {"pattern": args.pattern}
        demo = DemoSource("demo", width=width, height=height, fps=0, period_s=1e9, cfa="none", **options)
        frames = list(demo.frames(limit=args.frames))
        demo.close()
        camera = frames[0].camera
        source = "demo"
    ks = [0] + [int(k) for k in args.refresh.split(",")]
    streams = {k: Reconstructor(camera, workers=1, refresh=k) for k in ks}
    cpu = {k: [] for k in ks}
    stats = {k: [] for k in ks}
    diff = {k: [] for k in ks}
    pu21 = {k: [] for k in ks}
    digests = {k: hashlib.sha256() for k in ks}
    for i, frame in enumerate(frames):
        outs = {}
        for k in ks:
            t = time.thread_time()
            r = streams[k].process(frame)
            cpu[k].append(time.thread_time() - t)
            outs[k] = r.image
            for array in (r.image, r.motion, r.weight):
                digests[k].update(np.ascontiguousarray(array).tobytes())
            if truth is not None and i >= 8:
                pu21[k].append(pu21_psnr(r.image, truth))
            stats[k].append(streams[k].last_partial or {})
        for k in ks:
            ref = outs[0]
            diff[k].append(float(np.sqrt(np.mean(((outs[k] - ref) / np.maximum(ref, 1.0)) ** 2))))
    print(f"# {source} {args.size} mono {camera.pattern}, {args.frames} frames, load {os.getloadavg()[0]:.2f}; "
          "CPU ms per frame, median of frames 9..N (index 8..)")
    base = np.median(cpu[0][8:]) * 1e3
    for k in ks:
        c = np.median(cpu[k][8:]) * 1e3
        st = stats[k][8:]
        share = np.mean([s.get("computed", 0) / s["bands"] for s in st]) if k else 1.0
        line = f"refresh={k}: CPU {c:6.1f} ms (x{c / base:.2f})"
        if pu21[k]:
            line += f", PU21 {np.mean(pu21[k]):.3f} dB"
        if k:
            every = sum(s.get("computed") == s.get("bands") for s in st)
            line += (f", bands computed {100 * share:.1f} % (every band in {every} of {len(st)} frames), on demand: bands {np.mean([s.get('demand_bands', 0) for s in st]):.2f}"
                     f" cells {np.mean([s.get('demand_cells', 0) for s in st]):.1f} px {np.mean([s.get('demand_px', 0) for s in st]):.1f}"
                     f" kept {np.mean([s.get('kept_px', 0) for s in st]):.0f} /frame, completed {sum(bool(s.get('completed')) for s in st)}; rel. RMS diff vs off "
                     f"{np.median(diff[k][8:]):.4f}")
        print(line + f"; sha256 {digests[k].hexdigest()[:16]}", flush=True)
    print("per-frame CPU ms:", {k: [round(c * 1e3, 1) for c in cpu[k]] for k in ks})
    print("per-frame bands computed:", {k: [s.get("computed") for s in stats[k]] for k in ks if k})
    return 0


def bench_frames(image: str | None, pattern: str, noise: str, size: tuple[int, int], count: int):
    """(raw frames, camera, truth (float32 (H, W), DN at exposure 1), where from): ``svelive bench --live``'s
    timed frames (svelive.bench.live) of ``image`` (default Bonita of ../shared/data, else the shipped cannon
    crop) resized to ``size`` (rows, cols), seeds 0..count-1."""
    from pathlib import Path

    from svelive.bench.live import case_camera, case_radiance, resized, static_frames
    from svelive.bench.scenes import load_scene
    from svelive.simulation import sample_scene_path

    if image is None:
        shared = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "hdr" / "Bonita.exr"
        image = str(shared if shared.exists() else sample_scene_path("cannon"))
    camera = case_camera(pattern)
    scene = resized(load_scene(Path(image)), size)
    raws, truth = static_frames(case_radiance(pattern, noise, scene), camera, count, 0)
    return raws, camera, truth, f"bench {Path(image).stem} {noise}"


if __name__ == "__main__":
    sys.exit(main())
