"""The colour band refresh's prototype (issue 25, ``Reconstructor(refresh=K, colour_refresh=True)``): CPU per frame
of a still colour stream, refresh 0 against K, and how far its output moves.

    python benchmarks/settle_colour.py demo [--size 1920x1200] [--frames 24] [--refresh 8] [--workers 1]
    python benchmarks/settle_colour.py sim [--image DIR/Desk.exr ...] [--size 640x400] [--noise bright,dim]
    ... [--round-robin-only]   # a diagnostic: no band kept for its motion (the floor of the round-robin alone)

``demo``: the demo's colour camera (dual-ISO 1/1/8/8 on RGGB, a still view). The streams take the same frames in
turn, frame by frame in one process, the order alternated every frame; each frame's thread CPU time (one thread).
Prints the median over frames 9..N (index 8..), the share of the luminance's bands computed, on-demand counts and
the outputs' relative RMS difference (RGB, per value, against max(off, 1)) from the stream with refresh off.

``sim``: a still scene with truth (svelive.bench.live.static_frames with the bench's dual-ISO camera, the image
resized to ``--size``, the bench's noise levels): PU21-PSNR (dB; colour: luminance and R, G, B) of frames 9..N
against the truth, mean over those frames, for each stream, and the same CPU and difference figures.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def run_streams(camera, frames, ks: list[int], truth=None, workers: int = 1) -> dict:
    """Each stream of ``ks`` (0: off) over ``frames`` in turn, frame by frame, the order alternated; per stream the
    CPU (s) a frame (the calling thread's with one worker, else the process's: the streams' pools), its
    last_partial, its relative RMS difference from off and (with ``truth``) PU21."""
    from svelive.metrics import pu21_psnr_colour
    from svelive.reconstruction import Reconstructor

    streams = {k: Reconstructor(camera, workers=workers, refresh=k, colour_refresh=k > 0) for k in ks}
    clock = time.thread_time if workers == 1 else time.process_time
    out = {k: dict(cpu=[], stats=[], diff=[], pu21=[]) for k in ks}
    for i, frame in enumerate(frames):
        images = {}
        for k in (ks if i % 2 == 0 else ks[::-1]):
            t = clock()
            r = streams[k].process(frame)
            out[k]["cpu"].append(clock() - t)
            images[k] = r.image
            out[k]["stats"].append(streams[k].last_partial or {})
        for k in ks:
            ref = images[0]
            out[k]["diff"].append(float(np.sqrt(np.mean(((images[k] - ref) / np.maximum(ref, 1.0)) ** 2))))
            if truth is not None:
                out[k]["pu21"].append(pu21_psnr_colour(images[k], truth))
    for s in streams.values():
        s.close()
    return out


def report(out: dict, ks: list[int], first: int = 8) -> None:
    base = np.median(out[0]["cpu"][first:]) * 1e3
    for k in ks:
        o = out[k]
        c = np.median(o["cpu"][first:]) * 1e3
        line = f"refresh={k}: CPU {c:6.1f} ms (x{c / base:.2f})"
        if k:
            st = o["stats"][first:]
            share = np.mean([s.get("computed", s.get("bands", 1)) / s.get("bands", 1) for s in st])
            line += (f", bands computed {100 * share:.1f} % (per frame {[s.get('computed') for s in st]}), on demand: "
                     f"bands {np.mean([s.get('demand_bands', 0) for s in st]):.2f} cells "
                     f"{np.mean([s.get('demand_cells', 0) for s in st]):.1f} px "
                     f"{np.mean([s.get('demand_px', 0) for s in st]):.0f} kept "
                     f"{np.mean([s.get('kept_px', 0) for s in st]):.0f} /frame; rel. RMS diff vs off median "
                     f"{np.median(o['diff'][first:]):.4f}, last {o['diff'][-1]:.4f}")
        if o["pu21"]:
            p = o["pu21"][first:]
            line += "; PU21 " + ", ".join(f"{c} {np.mean([q[c] for q in p]):.2f}" for c in "YRGB")
        print(line, flush=True)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("mode", choices=("demo", "sim"))
    ap.add_argument("--size", default=None, help="WxH; demo 1920x1200, sim 640x400")
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--refresh", default="8")
    ap.add_argument("--image", nargs="*", default=["/work/shared/data/hdr/Desk.exr"])
    ap.add_argument("--noise", default="bright,dim")
    ap.add_argument("--workers", type=int, default=1, help="each stream's threads (CPU then the process's)")
    ap.add_argument("--round-robin-only", action="store_true",
                    help="a diagnostic: no band kept for its motion (settle.moving_bands says none), the round-robin's "
                         "floor")
    args = ap.parse_args()
    if args.round_robin_only:
        from svelive.reconstruction import settle
        settle.moving_bands = lambda band_motion, band_pixels, *a, **k: np.zeros(len(band_pixels), bool)
    from svelive.memory import keep_freed_memory
    keep_freed_memory()
    ks = [0] + [int(k) for k in args.refresh.split(",")]
    if args.mode == "demo":
        from svelive.capture.demo import DemoSource
        width, height = (int(v) for v in (args.size or "1920x1200").lower().split("x"))
        demo = DemoSource("demo", width=width, height=height, fps=0, period_s=1e9, cfa="RGGB")
        frames = list(demo.frames(limit=args.frames))
        demo.close()
        print(f"# demo {width}x{height} colour ({frames[0].camera.pattern}, {frames[0].camera.cfa}), "
              f"{args.frames} frames, {args.workers} worker(s), load {os.getloadavg()[0]:.2f}; "
              f"{'thread' if args.workers == 1 else 'process'} CPU ms a frame, median of frames 9..N")
        report(run_streams(frames[0].camera, frames, ks, workers=args.workers), ks)
        return 0
    from svelive.bench.live import case_camera, case_radiance, resized, static_frames
    from svelive.exr import read_exr
    width, height = (int(v) for v in (args.size or "640x400").lower().split("x"))
    camera = case_camera("dual-iso")
    for path in args.image:
        channels, _ = read_exr(path)
        scene = resized(np.stack([channels[c] for c in "RGB"], axis=-1).astype(np.float32), (height, width))
        for noise in args.noise.split(","):
            raws, truth = static_frames(case_radiance("dual-iso", noise, scene), camera, args.frames, 1)
            print(f"# {os.path.basename(path)} {width}x{height} dual-iso {noise}, {args.frames} frames, load "
                  f"{os.getloadavg()[0]:.2f}", flush=True)
            report(run_streams(camera, raws, ks, truth, args.workers), ks)
    return 0


if __name__ == "__main__":
    sys.exit(main())
