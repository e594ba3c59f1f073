"""How much of a live frame would need the method if still, settled regions were not reconstructed again.

    python benchmarks/still_tiles.py [--size 1920x1200] [--frames 24] [--cfa none|RGGB] [--tiles 32,64,128]

A measurement for issue 25's next structural step, not a feature: in a static view the temporal fusion's
history of a pixel is settled once it holds ``max_history`` frames, and a new frame adds 1 / max_history of
its estimate. A stream that reconstructed only the tiles holding a pixel the motion test reset within the
last ``max_history`` frames would pay the method on that share of the frame. This script streams the demo
camera's still view (new noise in every frame) through ``svelive.Reconstructor`` and prints, per frame
after the history has filled, the share of the frame's pixels flagged as moving (false alarms, since nothing
moves) and, per tile size, the share of tiles hit in this frame and the share hit in the last
``max_history`` frames (those a tile-wise stream would reconstruct), then their medians.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

_HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or ".") != _HERE]
sys.path.insert(0, os.path.dirname(_HERE))  # this checkout, not an editable install's


def tiles_hit(motion: np.ndarray, tile: int) -> np.ndarray:
    """bool (H // tile, W // tile): the whole tiles of ``motion`` (bool (H, W)) holding a flagged pixel."""
    h, w = motion.shape[0] // tile * tile, motion.shape[1] // tile * tile
    return motion[:h, :w].reshape(h // tile, tile, w // tile, tile).any(axis=(1, 3))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="1920x1200")
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--cfa", default="none")
    ap.add_argument("--tiles", default="32,64,128")
    args = ap.parse_args()
    from svelive.capture.demo import DemoSource
    from svelive.reconstruction import Reconstructor

    width, height = (int(v) for v in args.size.lower().split("x"))
    tiles = [int(t) for t in args.tiles.split(",")]
    demo = DemoSource("demo", width=width, height=height, fps=0, period_s=1e9, cfa=args.cfa)
    frames = list(demo.frames(limit=args.frames))
    demo.close()
    print(f"# demo {args.size} cfa {args.cfa}, a still view, {args.frames} frames", file=sys.stderr)
    rows: list[list[float]] = []
    with Reconstructor(frames[0].camera, workers=2) as stream:
        memory = stream.motion_config.max_history
        hits: dict[int, list[np.ndarray]] = {t: [] for t in tiles}
        for i, frame in enumerate(frames):
            motion = stream.process(frame).motion
            for t in tiles:
                hits[t].append(tiles_hit(motion, t))
            if i < 2 * memory - 1:
                print(f"frame {i + 1}/{len(frames)} (filling the history)", file=sys.stderr, flush=True)
                continue
            row = [100 * float(motion.mean())]
            for t in tiles:
                row += [100 * float(hits[t][-1].mean()), 100 * float(np.any(hits[t][-memory:], axis=0).mean())]
            rows.append(row)
            print(f"frame {i + 1}: moving {row[0]:.3f} % | " + " | ".join(
                f"{t} px: hit {row[1 + 2 * k]:.1f} %, last {memory} frames {row[2 + 2 * k]:.1f} %"
                for k, t in enumerate(tiles)), flush=True)
    if not rows:
        print(f"no frame after the history filled: give --frames > {2 * memory - 1}", file=sys.stderr)
        return 2
    med = np.median(np.array(rows), axis=0)
    print(f"median: moving {med[0]:.3f} % | " + " | ".join(
        f"{t} px: hit {med[1 + 2 * k]:.1f} %, last {memory} frames {med[2 + 2 * k]:.1f} %" for k, t in enumerate(tiles)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
