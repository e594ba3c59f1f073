"""The README's library stream without a noise model, against the single-frame default, in dim light (issue 26).

    .venv/bin/python benchmarks/library_noise.py [--quick] [--crop 320] [--shared-only | --shipped-only]
    .venv/bin/python benchmarks/library_noise.py --colour [--quick] [--moving]

Dim 12-bit scenes (black level 64, 4 and 5 stops under full scale) from the shipped crops
(svelive/data) and the shared HDR images (../shared/data/hdr, when present), rendered with a
true sensor that is NOT given to svelive (several full wells and read noises, far from the
defaults). Per scene, still and with a bright disc crossing it (20 px per frame), at frames 1, 2,
3 and 8, PU21-PSNR (dB) on still pixels (no motion in this frame or the three before) and on
moving pixels (the ground-truth mask), of:

- ``single``: ``svelive.reconstruct(raw, PATTERN, black_level=64, white_level=4095)`` per frame, the
  single-frame default (its noise model estimated from the frame);
- ``defaults``: ``Reconstructor(PATTERN, black_level=64, white_level=4095, gain=G0, read_noise=R0)`` with
  the fixed defaults (svelive.core.sensor) given: the README usage before issue 26.1;
- ``readme``: ``Reconstructor(PATTERN, black_level=64, white_level=4095)``, the README usage as it is;
- ``true``: the stream given the true gain and read noise (what the frames can give at best).

The columns print each stream minus ``single`` (dB); the last column is the ``readme`` stream's
noise estimate after frame 8 against the truth.

``--colour``: the same on colour streams (the colour layouts, the shipped RGB crops and the shared images'
RGB when present, still scenes), PU21 of Rec. 709 luminance: ``Reconstructor(layout pattern, cfa=...,
black_level=64, white_level=4095)`` and the true model given, against ``svelive.reconstruct`` of the frame.
The column ``ideal`` is ``svelive.reconstruct`` (true model) of one frame holding the light of FRAMES[-1]
frames (a 15-bit sensor of 8x the DN, the same gain, sqrt(8)x the read noise in DN: the noise of 8 frames
summed): what a reconstruction from every frame's readings at once gives, which fusion approaches at best.
``--stops 6,7``: other light levels than 4 and 5 stops under full scale (every table).
``--model-sensitivity``: the single-frame default on one still frame of each scene and sensor (bright, 4 and 5
stops under), given the true model with its gain scaled by 0.5, 2 and 4: PU21 of the frame minus that with the
true model, each case and the mean. Where a scaled model scores better, a stream (which uses a better model than a
single frame's own estimate) can lose to the single frame although the fusion leaves moving pixels as they are.
``--colour --moving``: a bright orange disc (3 stops over the scene's 99.9th percentile, radius a tenth of
the crop) crosses each scene at 20 px per frame; stream minus single (the ``true`` stream minus the single
frame given the true model too: the fusion's own effect) on still pixels (no motion in this
frame or the three before), moving pixels (the truth changed since the frame before) and trail pixels
(moved in the three frames before, still now), and the ghost residue (svelive.bench.motion_cases) of the
stream and the single frame on the trail, at frames 3 and 8.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # this checkout

import svelive  # noqa: E402
from svelive import Pattern, Sensor  # noqa: E402
from svelive.exr import read_luminance  # noqa: E402
from svelive.scenes import moving_disc, render_sequence, static  # noqa: E402
from svelive.simulation import exposure_scale  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from motion import region_pu21  # noqa: E402  (PU21-PSNR over a region, display scaling from the whole truth)

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data" / "hdr"
PATTERN = "1,4/16,64"
BLACK, WHITE = 64, 4095
#: true sensors (full well e-, read noise e-): none of them is given to svelive
SENSORS = ((40_000, 6.0), (3_000, 2.0), (10_000, 12.0))
STOPS = (4.0, 5.0)
FRAMES = (1, 2, 3, 8)
SHIPPED = ("desk", "mttamwest", "cannon")
SHARED_IMAGES = ("Desk", "Garden", "Bonita", "MtTamWest", "BrightRings")


def crop(image: np.ndarray, size: int) -> np.ndarray:
    """The centre ``size`` x ``size`` of ``image`` (or all of a smaller side)."""
    h, w = image.shape
    return image[(h - min(h, size)) // 2:][:size, (w - min(w, size)) // 2:][:, :size]


def scene_images(size: int, shipped: bool, shared: bool) -> list[tuple[str, np.ndarray]]:
    """(name, radiance float32 (H, W)) of the scenes measured."""
    out = []
    if shipped:
        out += [(name, crop(np.maximum(read_luminance(ROOT / "svelive" / "data" / f"{name}.exr"), 0), size))
                for name in SHIPPED]
    if shared and SHARED.is_dir():
        out += [(name, crop(np.maximum(read_luminance(SHARED / f"{name}.exr"), 0), size)) for name in SHARED_IMAGES]
    return out


def streams(sensor: Sensor) -> dict[str, svelive.Reconstructor]:
    """The streams compared, each fresh."""
    levels = dict(black_level=BLACK, white_level=WHITE)
    nominal = Sensor(12, BLACK, WHITE)
    return {"defaults": svelive.Reconstructor(PATTERN, **levels, gain=nominal.effective_gain,
                                              read_noise=nominal.effective_read_noise),
            "readme": svelive.Reconstructor(PATTERN, **levels),
            "true": svelive.Reconstructor(PATTERN, **levels, gain=sensor.gain, read_noise=sensor.read_noise)}


def measure(image: np.ndarray, sensor: Sensor, stops: float, moving: bool, seed: int) -> dict:
    """PU21 per stream, region and frame of one dim sequence; and the readme stream's final estimate."""
    radiance = image * exposure_scale(image, Pattern.parse(PATTERN), sensor, stops_below_fill=stops)
    n = max(FRAMES)
    if moving:
        h, w = radiance.shape
        peak = float(np.percentile(radiance, 99.9))
        scene = moving_disc(radiance, 2.0 * peak, radius=min(h, w) / 10, start=(h / 2, 0.1 * w), velocity=(0.0, 20.0))
    else:
        scene = static(radiance)
    frames = list(render_sequence(scene, n, PATTERN, sensor, seed=seed))
    runs = streams(sensor)
    out: dict = {}
    history = []
    for i, f in enumerate(frames, start=1):
        history.append(f.motion)
        still = ~np.any(history[-4:], axis=0)
        images = {"single": svelive.reconstruct(f.raw, PATTERN, black_level=BLACK, white_level=WHITE)}
        images.update({name: stream.process(f.raw).image for name, stream in runs.items()})
        if i in FRAMES:
            for name, x in images.items():
                out[("still", name, i)] = region_pu21(x, f.truth, still)
                if moving:
                    out[("moving", name, i)] = region_pu21(x, f.truth, f.motion)
    noise = getattr(runs["readme"], "noise", None)
    out["noise"] = None if noise is None else (noise.gain / sensor.gain - 1, noise.read_noise / sensor.read_noise - 1,
                                               noise.source)
    return out


GAIN_SCALES = (0.5, 2.0, 4.0)


def model_sensitivity_main(size: int, shipped: bool, shared: bool, stops: tuple[float, ...]) -> None:
    """``--model-sensitivity`` (module docstring): one line per case, then the mean and range per scale."""
    levels = dict(black_level=BLACK, white_level=WHITE)
    print(f"# pattern {PATTERN}, crops {size} px; single frame given the true model with its gain scaled, "
          f"PU21 minus that with the true model (dB)")
    deltas: dict[float, list[float]] = {g: [] for g in GAIN_SCALES}
    for label, image in scene_images(size, shipped, shared):
        for full_well, read_e in SENSORS:
            sensor = Sensor.from_full_well(12, full_well, read_e, black_level=BLACK, white_level=WHITE)
            for st in (0.0, *stops):
                radiance = image * exposure_scale(image, Pattern.parse(PATTERN), sensor, stops_below_fill=st)
                frame = next(iter(render_sequence(static(radiance), 1, PATTERN, sensor, seed=1)))
                everywhere = np.ones(frame.truth.shape, bool)

                def score(scale: float) -> float:
                    image_out = svelive.reconstruct(frame.raw, PATTERN, **levels, gain=sensor.gain * scale,
                                                    read_noise=sensor.read_noise)
                    return region_pu21(image_out, frame.truth, everywhere)

                true = score(1.0)
                row = {g: score(g) - true for g in GAIN_SCALES}
                for g, d in row.items():
                    deltas[g].append(d)
                print(f"{label:12s} {full_well:6.0f}e/{read_e:4.1f}e -{st:.0f}st true {true:5.2f} | "
                      + " ".join(f"x{g:g} {d:+5.2f}" for g, d in row.items()), flush=True)
    print("gain " + "  ".join(f"x{g:g} mean {np.mean(d):+.2f} (min {np.min(d):+.2f}, max {np.max(d):+.2f})"
                              for g, d in deltas.items()) + f" over {len(deltas[GAIN_SCALES[0]])} cases")


COLOUR_LAYOUTS = ("assorted-4x4", "dual-iso", "quad-bayer")


def colour_images(size: int, shared: bool) -> list[tuple[str, np.ndarray]]:
    """(name, linear RGB float32 (H, W, 3)) of the colour scenes: shipped crops, and shared images if asked."""
    from svelive.exr import read_exr
    from svelive.simulation import load_sample_scene

    out = [(name, np.maximum(load_sample_scene(name, rgb=True), 0)[:size, :size]) for name in SHIPPED]
    if shared and SHARED.is_dir():
        for name in SHARED_IMAGES:
            channels, _ = read_exr(SHARED / f"{name}.exr")
            if not all(c in channels for c in "RGB"):  # a luminance-only image (Garden)
                continue
            rgb = np.maximum(np.stack([channels[c] for c in "RGB"], axis=-1), 0).astype(np.float32)
            h, w, _ = rgb.shape
            out.append((name, rgb[(h - min(h, size)) // 2:][:size, (w - min(w, size)) // 2:][:, :size]))
    return out


def ideal_colour(scene: np.ndarray, pattern: str, cfa: str, sensor: Sensor, frames: int, seed: int) -> np.ndarray:
    """``svelive.reconstruct`` (true model) of one frame holding the light of ``frames`` frames: a sensor of
    ``frames`` x the DN (16 bits at most), the same gain, sqrt(frames) x the read noise in DN."""
    from svelive.simulation import simulate

    bits = min(16, 12 + int(np.ceil(np.log2(frames))))
    big = Sensor(bits, BLACK * frames, BLACK * frames + (WHITE - BLACK) * frames, sensor.gain,
                 sensor.read_noise * np.sqrt(frames))
    raw = simulate(scene * np.float32(frames), pattern, big, cfa=cfa, seed=seed).raw
    return svelive.reconstruct(raw, pattern, cfa=cfa, black_level=big.black_level, white_level=big.white_level,
                               gain=big.gain, read_noise=big.read_noise) / np.float32(frames)


def measure_colour(rgb: np.ndarray, layout: str, sensor: Sensor, stops: float, seed: int) -> dict:
    """PU21 of Rec. 709 luminance per stream ('readme', 'true', 'single') at FRAMES of a still colour scene,
    and ('ideal', FRAMES[-1]): :func:`ideal_colour`."""
    from svelive.core.camera import COLOUR_LAYOUTS as LAYOUTS
    from svelive.metrics import luminance, pu21_psnr
    from svelive.simulation import simulate

    pattern, cfa = LAYOUTS[layout]
    scene = rgb * np.float32(exposure_scale(rgb, Pattern.parse(pattern), sensor, stops_below_fill=stops))
    truth = luminance(scene)
    levels = dict(black_level=BLACK, white_level=WHITE)
    runs = {"readme": svelive.Reconstructor(pattern, cfa=cfa, **levels),
            "true": svelive.Reconstructor(pattern, cfa=cfa, **levels, gain=sensor.gain, read_noise=sensor.read_noise)}
    out = {}
    for i in range(1, max(FRAMES) + 1):
        raw = simulate(scene, pattern, sensor, cfa=cfa, seed=seed + i).raw
        images = {"single": svelive.reconstruct(raw, pattern, cfa=cfa, **levels)}
        images.update({name: stream.process(raw).image for name, stream in runs.items()})
        if i in FRAMES:
            for name, x in images.items():
                out[(name, i)] = pu21_psnr(luminance(x), truth)
    out[("ideal", max(FRAMES))] = pu21_psnr(luminance(ideal_colour(scene, pattern, cfa, sensor, max(FRAMES), seed)),
                                           truth)
    return out


def measure_colour_moving(rgb: np.ndarray, layout: str, sensor: Sensor, stops: float, seed: int) -> dict:
    """PU21 of Rec. 709 luminance per stream ('readme', 'true', 'single', 'single_true': the true model
    given to the single frame), region ('still', 'moving',
    'trail') and frame (3 and FRAMES[-1]), and the trail's ghost residue per stream and frame, of a
    colour scene that a bright orange disc crosses (module docstring)."""
    from svelive.bench.motion_cases import ghost_residue, region_masks, trail_before
    from svelive.core.camera import COLOUR_LAYOUTS as LAYOUTS
    from svelive.metrics import luminance
    from svelive.simulation import simulate

    pattern, cfa = LAYOUTS[layout]
    background = rgb * np.float32(exposure_scale(rgb, Pattern.parse(pattern), sensor, stops_below_fill=stops))
    h, w, _ = background.shape
    peak = float(np.percentile(background.max(axis=2), 99.9))
    yy, xx = np.mgrid[:h, :w]
    levels = dict(black_level=BLACK, white_level=WHITE)
    runs = {"readme": svelive.Reconstructor(pattern, cfa=cfa, **levels),
            "true": svelive.Reconstructor(pattern, cfa=cfa, **levels, gain=sensor.gain, read_noise=sensor.read_noise)}
    truths, motions, out = [], [], {}
    for i in range(1, max(FRAMES) + 1):
        disc = (yy - h / 2) ** 2 + (xx - 0.1 * w - 20 * (i - 1)) ** 2 <= (min(h, w) / 10) ** 2
        scene = background.copy()
        scene[disc] = np.float32([8.0, 4.0, 1.0]) * np.float32(peak)
        truths.append(luminance(scene))
        motions.append(np.zeros((h, w), bool) if i == 1 else truths[-1] != truths[-2])
        raw = simulate(scene, pattern, sensor, cfa=cfa, seed=seed + i).raw
        images = {"single": svelive.reconstruct(raw, pattern, cfa=cfa, **levels),
                  "single_true": svelive.reconstruct(raw, pattern, cfa=cfa, **levels, gain=sensor.gain,
                                                     read_noise=sensor.read_noise)}
        images.update({name: stream.process(raw).image for name, stream in runs.items()})
        if i in (3, max(FRAMES)):
            regions = region_masks(motions, i - 1)
            before = trail_before(motions, truths, i - 1)
            for name, x in images.items():
                y = luminance(x)
                for region, mask in regions.items():
                    out[(name, region, i)] = region_pu21(y, truths[-1], mask) if mask.any() else float("nan")
                out[(name, "ghost", i)] = ghost_residue(y, truths[-1], before, regions["trail"])
    return out


def colour_cases(quick: bool, size: int, shared: bool, stops: tuple[float, ...] = STOPS):
    """(label, rgb, layout, sensor, stops, seed) of every colour run, in the tables' order."""
    for name, rgb in colour_images(size, shared):
        for layout in COLOUR_LAYOUTS:
            for full_well, read_e in SENSORS[:2] if quick else SENSORS:
                sensor = Sensor.from_full_well(12, full_well, read_e, black_level=BLACK, white_level=WHITE)
                for st in stops[:1] if quick else stops:
                    yield (f"{name:11s} {layout:12s} {full_well:5d}e/{read_e:4.1f}e -{st:.0f}st", rgb, layout, sensor, st,
                           int(full_well + 10 * st))


def colour_moving_main(quick: bool, size: int, shared: bool, stops: tuple[float, ...] = STOPS) -> None:
    """The colour table with a moving disc (see the module docstring)."""
    print(f"# colour, a disc crossing, {size} px crops; stream minus single-frame default (dB), PU21 of luminance "
          "at frames 3 and 8: still moving trail; ghost residue (% of the change) stream / single")
    totals: dict = {}
    for label, rgb, layout, sensor, st, seed in colour_cases(quick, size, shared, stops):
        res = measure_colour_moving(rgb, layout, sensor, st, seed)
        cells = []
        for stream in ("readme", "true"):
            cell = []
            ref = "single" if stream == "readme" else "single_true"
            for i in (3, max(FRAMES)):
                d = [res[(stream, r, i)] - res[(ref, r, i)] for r in ("still", "moving", "trail")]
                for r, v in zip(("still", "moving", "trail"), d):
                    totals.setdefault((stream, r, i), []).append(v)
                g = (res[(stream, "ghost", i)], res[(ref, "ghost", i)])
                totals.setdefault((stream, "ghost", i), []).append(g[0] - g[1])
                cell.append(" ".join(f"{v:+5.2f}" for v in d) + f" g {100 * g[0]:+4.1f}/{100 * g[1]:+4.1f}")
            cells.append(f"{stream} " + " ; ".join(cell))
        print(f"{label} | {' | '.join(cells)}", flush=True)
    for stream in ("readme", "true"):
        for i in (3, max(FRAMES)):
            print(f"colour moving {stream:6s} f{i} " + "  ".join(
                f"{r} {np.nanmean(totals[(stream, r, i)]):+5.2f} (min {np.nanmin(totals[(stream, r, i)]):+5.2f})"
                for r in ("still", "moving", "trail"))
                + f"  ghost stream-single {100 * np.nanmean(totals[(stream, 'ghost', i)]):+.2f} % "
                  f"(max {100 * np.nanmax(totals[(stream, 'ghost', i)]):+.2f})")


def colour_main(quick: bool, size: int, shared: bool, stops: tuple[float, ...] = STOPS) -> None:
    """The colour table (see the module docstring)."""
    print(f"# colour, still, {size} px crops; stream minus single-frame default (dB), PU21 of luminance at frames {FRAMES}")
    totals: dict = {}
    for label, rgb, layout, sensor, st, seed in colour_cases(quick, size, shared, stops):
        res = measure_colour(rgb, layout, sensor, st, seed)
        cells = []
        for stream in ("readme", "true"):
            d = [res[(stream, i)] - res[("single", i)] for i in FRAMES]
            for i, v in zip(FRAMES, d):
                totals.setdefault((stream, i), []).append(v)
            cells.append(f"{stream} " + " ".join(f"{v:+5.2f}" for v in d))
        ideal = res[("ideal", max(FRAMES))] - res[("single", max(FRAMES))]
        totals.setdefault("ideal", []).append(ideal)
        print(f"{label} single f8 {res[('single', 8)]:5.2f} | {' | '.join(cells)} | ideal {ideal:+5.2f}", flush=True)
    for stream in ("readme", "true"):
        print(f"colour {stream:6s} " + "  ".join(f"f{i} {np.mean(totals[(stream, i)]):+5.2f} "
                                                  f"(min {np.min(totals[(stream, i)]):+5.2f})" for i in FRAMES))
    print(f"colour ideal  f{max(FRAMES)} {np.mean(totals['ideal']):+5.2f} (min {np.min(totals['ideal']):+5.2f})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one stop count, one sensor less, 256 px crops")
    parser.add_argument("--crop", type=int, default=320, help="crop side of the scenes (px)")
    parser.add_argument("--shared-only", action="store_true")
    parser.add_argument("--shipped-only", action="store_true")
    parser.add_argument("--colour", action="store_true", help="the colour streams' table instead")
    parser.add_argument("--moving", action="store_true", help="with --colour: a disc crossing each scene")
    parser.add_argument("--stops", type=lambda t: tuple(float(x) for x in t.split(",")), default=STOPS,
                        help="stops under full scale, comma-separated (default 4,5)")
    parser.add_argument("--model-sensitivity", action="store_true",
                        help="the single frame given the true model with its gain scaled instead")
    args = parser.parse_args()
    size = 256 if args.quick else args.crop
    if args.model_sensitivity:
        model_sensitivity_main(size, not args.shared_only, not args.shipped_only, args.stops)
        return
    if args.colour:
        (colour_moving_main if args.moving else colour_main)(args.quick, 128 if args.quick else 192,
                                                             not args.shipped_only, args.stops)
        return
    sensors = SENSORS[:2] if args.quick else SENSORS
    stops = args.stops[:1] if args.quick else args.stops
    scenes = scene_images(size, not args.shared_only, not args.shipped_only)
    names = ("defaults", "readme", "true")
    print(f"# pattern {PATTERN}, 12-bit, black {BLACK}, crops {size} px; stream minus single-frame default, dB, "
          f"PU21 at frames {FRAMES}")
    print(f"# columns: {' | '.join(names)}; each 'f1 f2 f3 f8'; noise: readme's estimate after frame 8 vs truth")
    totals: dict = {}
    t0 = time.perf_counter()
    for label, image in scenes:
        for full_well, read_e in sensors:
            sensor = Sensor.from_full_well(12, full_well, read_e, black_level=BLACK, white_level=WHITE)
            for st in stops:
                for moving in (False, True):
                    res = measure(image, sensor, st, moving, seed=int(full_well + 10 * st))
                    for region in ("still", "moving") if moving else ("still",):
                        cells = []
                        for name in names:
                            d = [res[(region, name, i)] - res[(region, "single", i)] for i in FRAMES]
                            for i, v in zip(FRAMES, d):
                                totals.setdefault((region, name, i), []).append(v)
                            cells.append(" ".join(f"{v:+5.2f}" for v in d))
                        noise = res["noise"]
                        nz = "" if noise is None else f"g {100 * noise[0]:+4.0f}% r {100 * noise[1]:+4.0f}% {noise[2]}"
                        scene = "moving" if moving else "still"
                        print(f"{label:11s} {full_well:5d}e/{read_e:4.1f}e -{st:.0f}st {scene:6s} {region:6s} "
                              f"single f8 {res[(region, 'single', 8)]:5.2f} | {' | '.join(cells)} | {nz}", flush=True)
    print("# summary over every run: stream minus single (dB): mean, min at each frame")
    for region in ("still", "moving"):
        for name in names:
            keys = [(region, name, i) for i in FRAMES]
            if keys[0] not in totals:
                continue
            cells = [f"f{i} {np.mean(totals[k]):+5.2f} (min {np.min(totals[k]):+5.2f})" for i, k in zip(FRAMES, keys)]
            print(f"{region:6s} {name:8s} " + "  ".join(cells))
    print(f"# {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
