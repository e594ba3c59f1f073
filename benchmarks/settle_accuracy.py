"""The band refresh (issue 25, svelive.reconstruction.settle): accuracy of ``Reconstructor(refresh=K)`` against
refresh off, on issue 26's cases.

    python benchmarks/settle_accuracy.py [--crop 256] [--frames 20] [--refresh 2,4] [--data ../shared/data]

benchmarks/motion.py's library scenes (a textured disc crossing a dim scene, stopping, a cut; Beachball), 10 000 e-
/ 12 e- sensor, 5 stops under, every stream given the true noise model (the fusion's own effect). Per case and
stream: PU21 (dB) of the still pixels at frames 8..N (mean), of the moving pixels at frames 2..N (mean and
worst), of the trail (mean), the ghost residue (%), and the share of bands the method ran on.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import motion  # noqa: E402  (benchmarks/motion.py)
from svelive import Sensor  # noqa: E402
from svelive.bench import motion_cases as mc  # noqa: E402
from svelive.reconstruction.stream import Reconstructor  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--crop", type=int, default=256)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--refresh", default="2,4")
    ap.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[1].parent / "shared" / "data")
    ap.add_argument("--cases", default="crossing,stops at 4,cut at 4,Beachball")
    ap.add_argument("--aggressive", action="store_true",
                    help="skip bands from the second frame on (no band runs for an unsettled history): the worst case")
    ap.add_argument("--sigmas", type=float, default=None, help="settle.UNSTABLE_SIGMAS")
    args = ap.parse_args()
    if args.sigmas:
        from svelive.reconstruction import settle
        settle.UNSTABLE_SIGMAS = args.sigmas
    if args.aggressive:
        from svelive.reconstruction import settle
        settle.UNSETTLED_SHARE = 2.0
    if args.data.exists():
        motion.DATA = args.data
    elif Path("/work/shared/data").exists():
        motion.DATA = Path("/work/shared/data")
    ks = [0] + [int(k) for k in args.refresh.split(",")]
    full_well, read_e, stops = 10_000, 12.0, 5.0
    sensor = Sensor.from_full_well(12, full_well, read_e, **motion.LIBRARY_LEVELS)
    true = dict(gain=sensor.gain, read_noise=sensor.read_noise)
    stats: dict[int, list[float]] = {}

    def factory(k):
        def make(raws):
            stream = Reconstructor(motion.PATTERN, **motion.LIBRARY_LEVELS, **true, refresh=k)
            original = stream.process

            def process(raw):
                out = original(raw)
                p = stream.last_partial
                if p is not None:
                    stats.setdefault(k, []).append(p["computed"] / p["bands"])
                return out
            stream.process = process
            return stream
        return make

    streams = {f"K={k}": factory(k) for k in ks}
    wanted = [c.strip() for c in args.cases.split(",")]
    print(f"# {args.crop} px, {args.frames} frames, {full_well} e- / {read_e} e-, {stops:.0f} stops under, true model; "
          "still 8..N, moving 2..N mean (worst), trail, ghost %; bands computed")
    for label, scene in motion.library_scenes(args.crop, stops, sensor, False):
        if not label.startswith("Desk/Bonita") and label != "Beachball":
            continue
        if not any(label.endswith(c) or label == c for c in wanted):
            continue
        stats.clear()
        scores = mc.run_case(scene, args.frames, motion.PATTERN, sensor, streams, {}, motion.region_pu21,
                             seed=int(full_well + 10 * stops))
        cells = []
        for name in streams:
            still = np.array(scores.pu21[(name, "still")][7:])
            moving = np.array(scores.pu21[(name, "moving")][1:])
            trail = np.array(scores.pu21[(name, "trail")][1:])
            ghost = np.nanmean(scores.ghost[name][1:])
            k = int(name[2:])
            share = np.mean(stats.get(k, [1.0])[8:]) if k else 1.0
            cells.append(f"{name} still {np.nanmean(still):6.2f} mov {np.nanmean(moving):6.2f} ({np.nanmin(moving):6.2f}) "
                         f"trail {np.nanmean(trail):6.2f} ghost {100 * ghost:+5.1f}% bands {100 * share:3.0f}%")
        print(f"{label:28s} | " + " | ".join(cells), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
