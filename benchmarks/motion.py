"""Motion robustness targets (issue 5): temporal fusion gain, moving regions, ghosting, integration timing, cost.

    python benchmarks/motion.py [--quick] [--cost-only] [--method NAME] [--figure docs/motion-trail.png]
    python benchmarks/motion.py --library-only [--quick]     # issue 26's cases (below)

Real HDR content from ../shared/data (not shipped). 12-bit sensor, 10 000 e- full
well, 3 e- read noise, pattern 1,4/16,64, the stream's default method (or
``--method``). PU21-PSNR is computed over a region (static or moving pixels of
the ground-truth motion mask) with the display scaling of the whole frame's
truth. "single" is one frame of the single-frame default (svelive.reconstruct's),
what a user gets without a stream; where the stream's method is another, its own
single frame is printed beside it.

``--library`` / ``--library-only``: issue 26's cases (svelive.bench.motion_cases), the library's stream as the
README uses it (no noise model: it estimates its own) and as the service runs it (the model of
``stream_noise`` on the first three frames given), against the single-frame default, in dim light with true
sensors the streams are not told: a bright textured object (a disc cut from another image) crossing a dark
scene at 22 px a frame, stopping at frame 4, starting at frame 4, a cut to another scene at frame 4, the
Beachball frames dimmed, and the same on procedural scenes that are in no image set. Per case, stream minus
single (dB): moving pixels (mean over frames 2-10 and the worst frame), still pixels at frame 8, the trail's
PU21 and ghost residue (the share of a change the output still shows; svelive.bench.motion_cases). A third
stream, ``true``, is given the true model and compared with the single frame given it too: the fusion's own
effect, apart from how the single-frame method responds to a different noise model.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # this checkout, not an editable install's

from svelive import Pattern, Sensor  # noqa: E402
from svelive.exr import read_luminance  # noqa: E402
from svelive.metrics import PU21_PEAK, display_scale, pu21_encode  # noqa: E402
from svelive.reconstruction.methods import DEFAULT_METHOD  # noqa: E402
from svelive.reconstruction.stream import Reconstructor  # noqa: E402
from svelive.scenes import load_beachball, moving_disc, panning, placed_frames, render_sequence, static  # noqa: E402
from svelive.simulation import exposure_scale  # noqa: E402

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
PATTERN = "1,4/16,64"
SENSOR = Sensor.from_full_well(12, 10_000, 3)
KW = dict(white_level=SENSOR.white_level, gain=SENSOR.gain, read_noise=SENSOR.read_noise)


def region_pu21(test: np.ndarray, truth: np.ndarray, region: np.ndarray) -> float:
    """PU21-PSNR (dB) over ``region`` only, display scaling from the whole truth."""
    if not region.any():
        return float("nan")
    s = display_scale(truth)
    err = pu21_encode(test[region] * s) - pu21_encode(truth[region] * s)
    mse = float(np.mean(err * err))
    return float("inf") if mse == 0 else 10 * np.log10(PU21_PEAK**2 / mse)


def scaled(image: np.ndarray, stops: float) -> np.ndarray:
    return image * exposure_scale(image, Pattern.parse(PATTERN), SENSOR, stops_below_fill=stops)


#: The stream's method (``--method``; None: the stream's default).
STREAM_METHOD: list[str | None] = [None]


def run(frames, **kw):
    """Fused and single-frame results of a rendered sequence: list of (frame, fused, single, own single).

    single: the single-frame default; own single: the stream's method on one frame (the same
    result when the stream uses the single-frame default)."""
    fused = Reconstructor(PATTERN, method=STREAM_METHOD[0], **KW, **kw)
    single = Reconstructor(PATTERN, temporal=False, method=DEFAULT_METHOD, **KW, **kw)
    own = single if fused.method == DEFAULT_METHOD else Reconstructor(PATTERN, temporal=False,
                                                                       method=fused.method, **KW, **kw)
    out = []
    for f in frames:
        a, b = fused.process(f.raw), single.process(f.raw)
        out.append((f, a, b, b if own is single else own.process(f.raw)))
    return out


def static_gain(name: str, stops: float, n: int, crop: int) -> tuple[float, float, float, float]:
    """(single default, fused, false-alarm fraction, single of the stream's method) of a static scene."""
    image = np.maximum(read_luminance(DATA / "hdr" / name), 0)
    h, w = image.shape
    image = image[(h - min(h, crop)) // 2:][:crop, (w - min(w, crop)) // 2:][:, :crop]
    out = run(render_sequence(static(scaled(image, stops)), n, PATTERN, SENSOR, seed=1))
    f, fused, single, own = out[-1]
    everywhere = np.ones(f.truth.shape, bool)
    false_alarm = float(np.mean([r.moving_fraction for _, r, _, _ in out[1:]]))
    return (region_pu21(single.image, f.truth, everywhere), region_pu21(fused.image, f.truth, everywhere),
            false_alarm, region_pu21(own.image, f.truth, everywhere))


def moving_case(label: str, scene, n: int, timing: str = "mask") -> dict[str, float]:
    out = run(render_sequence(scene, n, PATTERN, SENSOR, timing=timing, seed=3), exposure_timing=timing)
    moving = [f.motion for f, _, _, _ in out]
    trail_f, trail_s, mov_f, mov_s, st_f, st_s, mov_o = [], [], [], [], [], [], []
    for i, (f, fused, single, own) in enumerate(out[2:], start=2):
        # Trail: pixels that moved in the last 3 frames but are static now.
        trail = np.any(moving[max(0, i - 3):i], axis=0) & ~f.motion
        trail_f.append(region_pu21(fused.image, f.truth, trail))
        trail_s.append(region_pu21(single.image, f.truth, trail))
        mov_f.append(region_pu21(fused.image, f.truth, f.motion))
        mov_s.append(region_pu21(single.image, f.truth, f.motion))
        mov_o.append(region_pu21(own.image, f.truth, f.motion))
        st_f.append(region_pu21(fused.image, f.truth, ~f.motion))
        st_s.append(region_pu21(single.image, f.truth, ~f.motion))
    res = {k: float(np.nanmean(v)) for k, v in dict(moving_fused=mov_f, moving_single=mov_s, trail_fused=trail_f,
                                                     trail_single=trail_s, static_fused=st_f,
                                                     static_single=st_s, moving_own=mov_o).items()}
    res["moving_fraction_gt"] = float(np.mean([m.mean() for m in moving]))
    res["flagged_fraction"] = float(np.mean([r.moving_fraction for _, r, _, _ in out[1:]]))
    own = "" if out[0][3] is out[0][2] else f" (own single {res['moving_own']:6.2f})"
    print(f"{label:34s} moving {res['moving_single']:6.2f} -> {res['moving_fused']:6.2f} dB{own} | "
          f"trail {res['trail_single']:6.2f} -> {res['trail_fused']:6.2f} dB | static {res['static_single']:6.2f} -> "
          f"{res['static_fused']:6.2f} dB | gt moving {100 * res['moving_fraction_gt']:.1f}% flagged "
          f"{100 * res['flagged_fraction']:.1f}%")
    return res


def integration_edge(scene, n: int) -> None:
    frames = list(render_sequence(scene, n, PATTERN, SENSOR, timing="integration", seed=5))
    for temporal in (False, True):
        method = STREAM_METHOD[0] if temporal else None
        with_c = Reconstructor(PATTERN, temporal=temporal, method=method, exposure_timing="integration", **KW)
        without = Reconstructor(PATTERN, temporal=temporal, method=method, exposure_timing="integration",
                                consistency=False, **KW)
        a = [(with_c.process(f.raw).image, f) for f in frames][1:]
        b = [(without.process(f.raw).image, f) for f in frames][1:]
        for region in ("moving", "static"):
            pick = (lambda f: f.motion) if region == "moving" else (lambda f: ~f.motion)  # noqa: E731
            pa = np.mean([region_pu21(x, f.truth, pick(f)) for x, f in a])
            pb = np.mean([region_pu21(x, f.truth, pick(f)) for x, f in b])
            print(f"  {'fused' if temporal else 'single-frame'} {region:7s} PU21 without consistency {pb:6.2f} dB, "
                  f"with {pa:6.2f} dB")


def cost(repeats: int) -> None:
    sys.path.insert(0, str(Path(__file__).parent))
    from speed import test_frame

    raw, sensor = test_frame(PATTERN)
    kw = dict(white_level=sensor.white_level, gain=sensor.gain, read_noise=sensor.read_noise)
    for label, opts in [("temporal + detail (mask)", {}), ("temporal, no detail", dict(detail=False)),
                        ("temporal + consistency (integration)", dict(exposure_timing="integration")),
                        ("single frame, no motion stage", dict(temporal=False))]:
        method = STREAM_METHOD[0] if opts.get("temporal", True) else None
        r = Reconstructor(PATTERN, method=method, **kw, **opts)
        method, motion = [], []
        for _ in range(repeats + 1):
            res = r.process(raw)
            method.append(res.timings_ms["method"])
            motion.append(res.timings_ms["motion"])
        print(f"1920x1200 {label:38s} {r.method:9s} method {np.median(method[1:]):6.1f} ms, motion stage "
              f"{np.median(motion[1:]):6.1f} ms (median of {repeats})")


LIBRARY_LEVELS = dict(black_level=64, white_level=4095)
#: true sensors of the library cases (full well e-, read noise e-), none given to the README stream
LIBRARY_SENSORS = ((3_000, 2.0), (10_000, 12.0), (40_000, 6.0))
LIBRARY_FRAMES = 10


def library_scenes(crop: int, stops: float, sensor: Sensor, procedural: bool) -> list[tuple[str, object]]:
    """(label, scene) of issue 26's cases at ``stops`` under full scale: shared images, or procedural ones."""
    from svelive.bench import motion_cases as mc

    def load(name: str) -> np.ndarray:
        image = np.maximum(read_luminance(DATA / "hdr" / f"{name}.exr"), 0)
        h, w = image.shape
        return image[(h - min(h, crop)) // 2:][:crop, (w - min(w, crop)) // 2:][:, :crop]

    if procedural:
        pairs = [("proc-1", mc.procedural_scene((crop, crop), 1), mc.procedural_scene((crop, crop), 2, slope=1.5)),
                 ("proc-3", mc.procedural_scene((crop, crop), 3, stops=14), mc.procedural_scene((crop, crop), 4))]
    else:
        pairs = [("Desk/Bonita", load("Desk"), load("Bonita")), ("MtTamWest/Cannon", load("MtTamWest"), load("Cannon")),
                 ("Garden/BrightRings", load("Garden"), load("BrightRings"))]
    out = []
    for label, back, other in pairs:
        background = mc.dim(back, PATTERN, sensor, stops)
        # the object: 3 stops brighter than the scene's 99.9th percentile at its own, textured
        texture = other * (8 * float(np.percentile(background, 99.9)) / max(float(np.percentile(other, 99.9)), 1e-12))
        radius = crop / 8
        crossing = mc.moving_texture(background, texture, radius, (crop / 2, radius + 4), (0.0, 22.0))
        out += [(f"{label} crossing", crossing), (f"{label} stops at 4", mc.stopping(crossing, 4.0)),
                (f"{label} starts at 4", mc.starting(crossing, 4.0)),
                (f"{label} cut at 4", mc.cut(crossing, mc.moving_texture(mc.dim(other, PATTERN, sensor, stops),
                                                                          back * (texture.max() / max(back.max(), 1e-12)),
                                                                          radius, (crop / 3, crop - radius - 4),
                                                                          (8.0, -18.0)), 4))]
    if not procedural:
        frames, shape = load_beachball(DATA / "beachball", scale=0.25)
        peak = max(float(np.percentile(f[0], 99.9)) for f in frames)
        scale = mc.dim(np.ones(1, np.float32), PATTERN, sensor, stops)[0] / peak  # 99.9th percentile to `stops` under
        out.append(("Beachball", placed_frames([(f * scale, o) for f, o in frames], shape, background=0.02 * peak * scale)))
    return out


def library_cases(crop: int, quick: bool) -> None:
    """Issue 26's table (see the module docstring)."""
    import svelive
    from svelive.bench import motion_cases as mc
    from svelive.reconstruction.stream import stream_noise

    sensors = LIBRARY_SENSORS[:2] if quick else LIBRARY_SENSORS
    stops_list = (5.0,) if quick else (4.0, 5.0)
    camera = svelive.Camera.build(PATTERN, None, Sensor(12, **LIBRARY_LEVELS))

    def service(raws):
        noise = stream_noise(raws[:3], camera)
        return Reconstructor(PATTERN, **LIBRARY_LEVELS, gain=noise.gain, read_noise=noise.read_noise)

    streams = {"readme": lambda raws: Reconstructor(PATTERN, **LIBRARY_LEVELS), "service": service}
    singles = {"single": lambda raw: svelive.reconstruct(raw, PATTERN, **LIBRARY_LEVELS)}
    baseline = dict.fromkeys(streams, "single")
    print(f"## issue 26 cases: {LIBRARY_FRAMES} frames, {crop} px, 12-bit, black 64; stream minus single-frame default "
          "(dB): moving mean (worst frame) over frames 2-10, still at frame 8, trail PU21 mean; ghost residue "
          "(% of the change shown, stream / single); 'true': the stream given the true model against the single frame "
          "given it")
    totals: dict[tuple[str, str], list[float]] = {}
    for procedural in (False, True):
        for full_well, read_e in sensors:
            sensor = Sensor.from_full_well(12, full_well, read_e, **LIBRARY_LEVELS)
            true = dict(gain=sensor.gain, read_noise=sensor.read_noise)
            # the fusion's own effect: a stream and the single frame given one model (the true one)
            both = dict(streams, true=lambda raws: Reconstructor(PATTERN, **LIBRARY_LEVELS, **true))
            both_singles = dict(singles, **{"single true": lambda raw: svelive.reconstruct(raw, PATTERN,
                                                                                         **LIBRARY_LEVELS, **true)})
            for stops in stops_list:
                for label, scene in library_scenes(crop, stops, sensor, procedural):
                    scores = mc.run_case(scene, LIBRARY_FRAMES, PATTERN, sensor, both, both_singles, region_pu21,
                                         seed=int(full_well + 10 * stops))
                    cells = []
                    for name in both:
                        one = baseline.get(name, "single true")
                        d = {region: np.array(scores.pu21[(name, region)]) - np.array(scores.pu21[(one, region)])
                             for region in ("moving", "still", "trail")}
                        moving = d["moving"][1:]
                        ghost, ghost_single = np.nanmean(scores.ghost[name][1:]), np.nanmean(scores.ghost[one][1:])
                        row = dict(moving=np.nanmean(moving), worst=np.nanmin(moving),
                                   still8=np.nan if "cut" in label else d["still"][7],  # after a cut: 4 frames
                                   trail=np.nanmean(d["trail"][1:]), ghost=ghost - ghost_single)
                        for key, value in row.items():
                            totals.setdefault((name, key), []).append(float(value))
                        cells.append(f"{name} mov {row['moving']:+5.2f} ({row['worst']:+5.2f}) still8 {row['still8']:+5.2f} "
                                     f"trail {row['trail']:+5.2f} ghost {100 * ghost:+4.1f}/{100 * ghost_single:+4.1f}%")
                    print(f"{label:30s} {full_well:5d}e/{read_e:4.1f}e -{stops:.0f}st | " + " | ".join(cells), flush=True)
    print("# summary (dB; ghost: stream minus single, % of the change): mean, worst; 'true': the stream and the "
          "single frame given the true model; still8 leaves out the cuts (4 frames since)")
    for name in (*streams, "true"):
        parts = []
        for key in ("moving", "worst", "still8", "trail", "ghost"):
            v = np.array(totals[(name, key)])
            v = v[np.isfinite(v)]
            scale, unit = (100, "%") if key == "ghost" else (1, "")
            worst = v.max() if key == "ghost" else v.min()
            parts.append(f"{key} {scale * v.mean():+5.2f}{unit} ({scale * worst:+5.2f}{unit})")
        print(f"{name:8s} " + "  ".join(parts))


def trail_figure(path: Path, scene, n: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = run(render_sequence(scene, n, PATTERN, SENSOR, seed=7))
    f, fused, single, _ = out[-1]
    s = display_scale(f.truth)
    tone = lambda x: pu21_encode(x * s) / PU21_PEAK  # noqa: E731
    err = lambda x: np.abs(pu21_encode(x * s) - pu21_encode(f.truth * s))  # noqa: E731
    panels = [("ground truth", tone(f.truth)), ("fused (8 frames)", tone(fused.image)),
              ("single frame", tone(single.image)), ("|error| fused, PU21", err(fused.image)),
              ("|error| single, PU21", err(single.image)), ("motion mask (flagged)", fused.motion)]
    fig, axes = plt.subplots(2, 3, figsize=(12, 8))
    vmax = float(np.percentile(err(single.image), 99.5))
    for ax, (title, img) in zip(axes.flat, panels):
        ax.imshow(img, cmap="gray" if "error" not in title else "magma",
                  vmax=vmax if "error" in title else None)
        ax.set_title(title)
        ax.axis("off")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    print(f"figure written to {path}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smaller crops and fewer repeats")
    parser.add_argument("--figure", type=Path, help="write the trail figure (frame, truth, error maps) here")
    parser.add_argument("--cost-only", action="store_true", help="only the 1920x1200 cost per frame")
    parser.add_argument("--method", help="the stream's single-frame method (default: the stream's default)")
    parser.add_argument("--no-cost", action="store_true", help="leave out the 1920x1200 cost per frame")
    parser.add_argument("--repeats", type=int, default=None, help="frames timed in the cost table")
    parser.add_argument("--library", action="store_true", help="also issue 26's cases of the library's stream")
    parser.add_argument("--library-only", action="store_true", help="only issue 26's cases")
    args = parser.parse_args()
    STREAM_METHOD[0] = args.method
    cv2.setNumThreads(1)
    crop, repeats = (256, 3) if args.quick else (512, 7)
    if args.repeats:
        repeats = args.repeats
    if args.cost_only:
        cost(args.repeats or 15)
        return
    if args.library_only:
        library_cases(crop // 2, args.quick)
        return
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, one thread; pattern {PATTERN}, "
          f"12-bit, 10000 e- full well, 3 e- read noise; 8 frames")
    print("## static scenes: PU21-PSNR single frame -> fused after 8 frames; mean flagged fraction (false alarms)")
    for stops in (5, 0):
        for name in ("Desk.exr", "MtTamWest.exr", "Bonita.exr", "Garden.exr", "Cannon.exr", "BrightRings.exr"):
            single, fused, fa, own = static_gain(name, stops, 8, crop)
            mine = "" if own == single else f" (own single {own:6.2f})"
            print(f"{stops} stops below fill {name:16s} {single:6.2f} -> {fused:6.2f} dB ({fused - single:+.2f}){mine}, "
                  f"false alarms {100 * fa:.3f}%")
    print("## moving scenes (mask timing unless stated): PU21 over ground-truth moving / trail / static pixels, "
          "single -> fused")
    mt = np.maximum(read_luminance(DATA / "hdr" / "MtTamWest.exr"), 0)
    desk = np.maximum(read_luminance(DATA / "hdr" / "Desk.exr"), 0)
    moving_case("pan 3 px/frame MtTamWest (all move)", panning(scaled(mt, 0), (crop, crop), (0.0, 3.0), (100, 100)), 8)
    dark = scaled(desk, 5)[:crop, :crop]
    disc = moving_disc(dark, float(np.percentile(dark, 99.9)) * 4, crop / 10, (crop / 2, crop / 5), (0.0, crop / 16))
    moving_case("bright disc over dark Desk, 5 stops", disc, 8)
    frames, shape = load_beachball(DATA / "beachball", scale=0.25)
    peak = max(float(np.percentile(f[0], 99.9)) for f in frames)
    ball = placed_frames([(f * (SENSOR.range_dn / peak), o) for f, o in frames], shape, background=2.0)
    moving_case("Beachball (data windows placed)", ball, 8)
    moving_case("Beachball, integration timing", ball, 8, timing="integration")
    print("## integration timing: within-frame consistency test on/off (frames 2..n)")
    for label, scene in [("bright disc over dark Desk", disc), ("Beachball", ball),
                         ("pan 3 px/frame MtTamWest", panning(scaled(mt, 0), (crop, crop), (0.0, 3.0), (100, 100)))]:
        print(label)
        integration_edge(scene, 6)
    if not args.no_cost:
        cost(repeats)
    if args.figure:
        trail_figure(args.figure, disc, 8)
    if args.library:
        library_cases(crop // 2, args.quick)


if __name__ == "__main__":
    main()
