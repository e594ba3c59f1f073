"""The band refresh (issue 25, svelive.reconstruction.settle): accuracy of ``Reconstructor(refresh=K)`` against
refresh off, on issue 26's cases.

    python benchmarks/settle_accuracy.py [--crop 256] [--frames 20] [--refresh 2,4] [--data ../shared/data]
    python benchmarks/settle_accuracy.py --cfa RGGB ...   # colour: dual-ISO on RGGB, colour_refresh

benchmarks/motion.py's library scenes (a textured disc crossing a dim scene, stopping, a cut; Beachball), 10 000 e-
/ 12 e- sensor, 5 stops under, every stream given the true noise model (the fusion's own effect). Per case and
stream: PU21 (dB) of the still pixels at frames 8..N (mean), of the moving pixels at frames 2..N (mean and
worst), of the trail (mean), the ghost residue (%), and the share of bands the method ran on.

``--cfa RGGB``: the same crossing, stopping and cut cases made of the images' RGB (each channel moved as the
monochrome case moves its one; no Beachball, which has no colour), the 1/1/8/8 exposures on an RGGB filter (the
demo's dual-ISO camera), each frame the mean of the scene at 8 instants of it, simulated with
svelive.simulation.simulate; streams ``Reconstructor(camera, refresh=K, colour_refresh=True)``; PU21 and ghost on
the luminance (Rec.709 weights of camera RGB, output and truth alike), motion where it changed by 5 % of the
larger (the monochrome renderer's rule).
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
from svelive import Camera, Sensor  # noqa: E402
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
    ap.add_argument("--cfa", default=None, help="a colour filter (RGGB): the colour cases, dual-ISO exposures")
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

    camera = Camera.build("1/1/8/8", args.cfa, sensor) if args.cfa else None

    def factory(k):
        def make(raws):
            stream = (Reconstructor(camera, refresh=k, colour_refresh=k > 0) if camera is not None
                      else Reconstructor(motion.PATTERN, **motion.LIBRARY_LEVELS, **true, refresh=k))
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
    colour_scenes = colour_library_scenes(args.crop, stops, sensor, "1/1/8/8") if args.cfa else {}
    for label, scene in motion.library_scenes(args.crop, stops, sensor, False):
        if not label.startswith("Desk/Bonita") and label != "Beachball":
            continue
        if args.cfa and label not in colour_scenes:
            continue
        if not any(label.endswith(c) or label == c for c in wanted):
            continue
        stats.clear()
        if args.cfa:
            scores = colour_case(colour_scenes[label], args.frames, camera, streams, seed=int(full_well + 10 * stops))
        else:
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


def colour_library_scenes(crop: int, stops: float, sensor, pattern: str) -> dict:
    """label -> RGB scene (t -> float32 (H, W, 3)) of motion.library_scenes' Desk/Bonita cases, each channel moved
    as the monochrome case moves its one (the same disc, texture scale and speeds)."""
    from svelive.exr import read_exr

    def load(name: str) -> np.ndarray:
        channels, _ = read_exr(motion.DATA / "hdr" / f"{name}.exr")
        image = np.maximum(np.stack([channels[c] for c in "RGB"], axis=-1), 0)
        h, w = image.shape[:2]
        return image[(h - min(h, crop)) // 2:][:crop, (w - min(w, crop)) // 2:][:, :crop]

    back, other = load("Desk"), load("Bonita")
    background = mc.dim(back, pattern, sensor, stops)
    texture = other * (8 * float(np.percentile(background, 99.9)) / max(float(np.percentile(other, 99.9)), 1e-12))
    radius = crop / 8

    def crossing_of(bg, tex, centre, velocity):
        parts = [mc.moving_texture(bg[..., c], tex[..., c], radius, centre, velocity) for c in range(3)]
        return lambda t: np.stack([p(t) for p in parts], axis=-1)

    crossing = crossing_of(background, texture, (crop / 2, radius + 4), (0.0, 22.0))
    second = crossing_of(mc.dim(other, pattern, sensor, stops), back * (texture.max() / max(back.max(), 1e-12)),
                         (crop / 3, crop - radius - 4), (8.0, -18.0))
    return {"Desk/Bonita crossing": crossing, "Desk/Bonita stops at 4": mc.stopping(crossing, 4.0),
            "Desk/Bonita starts at 4": mc.starting(crossing, 4.0), "Desk/Bonita cut at 4": mc.cut(crossing, second, 4)}


def colour_case(scene, frames: int, camera, streams: dict, seed: int, samples: int = 8) -> mc.CaseScores:
    """:func:`svelive.bench.motion_cases.run_case` for an RGB ``scene``: each frame the mean of the scene at
    ``samples`` instants within it, simulated through ``camera`` (its CFA); PU21 and ghost residue on the
    luminance (Rec.709 weights, float32 (H, W))."""
    from svelive.simulation import simulate

    weights = np.array([0.2126, 0.7152, 0.0722], np.float32)
    truths, lums, raws = [], [], []
    for i in range(frames):
        radiance = np.mean([scene(i + (k + 0.5) / samples) for k in range(samples)], axis=0).astype(np.float32)
        raws.append(simulate(radiance, camera.pattern, camera.sensor, cfa=camera.cfa, seed=seed + i).raw)
        truths.append(radiance)
        lums.append(radiance @ weights)
    motions = [np.zeros(lums[0].shape, bool)]
    floor = 1e-3 * float(np.percentile(lums[0], 99.9))
    for a, b in zip(lums, lums[1:]):
        change = np.abs(b - a)
        motions.append((change > 0.05 * np.maximum(a, b)) & (change > floor))
    made = {name: factory(raws) for name, factory in streams.items()}
    scores = mc.CaseScores({}, {})
    for i, raw in enumerate(raws):
        regions = mc.region_masks(motions, i)
        before = mc.trail_before(motions, lums, i)
        for name, stream in made.items():
            image = stream.process(raw).image @ weights
            for region, mask in regions.items():
                scores.pu21.setdefault((name, region), []).append(
                    motion.region_pu21(image, lums[i], mask) if mask.any() else float("nan"))
            scores.ghost.setdefault(name, []).append(mc.ghost_residue(image, lums[i], before, regions["trail"]))
    return scores


if __name__ == "__main__":
    sys.exit(main())
