"""The ``svelive calibrate response|mask|noise`` verbs."""

from __future__ import annotations

import argparse
import json
import math
import struct
import sys
import time
from pathlib import Path

import numpy as np

from svelive.calibrate.mask import MaskConfig, estimate_mask, parse_tile, save_mask
from svelive.calibrate.noise import calibrate_noise
from svelive.calibrate.response import SWEEP_KNOTS, ResponseFitConfig, fit_response, save_response, write_json
from svelive.cli import existing_file, parse_times
from svelive.cli.reconstruct import read_raw
from svelive.core.atomic import check_output_target
from svelive.core.camera import Camera, one_colour_plane
from svelive.core.errors import SveliveError
from svelive.core.pattern import Pattern
from svelive.core.sensor import Sensor, container_bits
from svelive.options import CameraSettings, add_camera_option, build_camera, parse_cfa


def png_significant_bits(path: Path) -> int | None:
    """The bit depth a PNG's sBIT chunk declares for a grey image (e.g. 12 in a 16-bit file), or None."""
    if path.suffix.lower() != ".png":
        return None
    try:
        with open(path, "rb") as f:
            if f.read(8) != b"\x89PNG\r\n\x1a\n":
                return None
            while True:
                head = f.read(8)
                if len(head) < 8:
                    return None
                length, kind = struct.unpack(">I4s", head)
                if kind == b"sBIT":
                    return int(f.read(length)[0])
                if kind in (b"IDAT", b"IEND"):  # sBIT comes before the image data
                    return None
                f.seek(length + 4, 1)
    except (OSError, IndexError, struct.error):
        return None


def saturation_bits(raw: np.ndarray) -> int | None:
    """The bit depth b (9..16) whose white, 2^b - 1, is the frame's maximum and is held by a cluster
    of pixels (at least 16 and 1/10000 of the frame): the evidence a saturated 12-bit frame in a
    16-bit file gives. None when the maximum is not such a value."""
    top = int(raw.max())
    bits = top.bit_length()
    if top != 2**bits - 1 or not 9 <= bits <= 16:
        return None
    return bits if int(np.count_nonzero(raw == top)) >= max(16, raw.size // 10000) else None


def sensor_from_args(raw: np.ndarray, args: argparse.Namespace, path: Path | None = None,
                     required: bool = True) -> Sensor:
    """Sensor levels from --bits/--black-level/--white-level.

    Without --bits the bit depth is, in order: the one --white-level implies, the PNG's sBIT
    chunk, 8 for an 8-bit file, or a cluster of readings at 2^b - 1 (a saturated frame); a
    16-bit file with none of these is refused with a message naming --bits (``required``) or
    taken as 16 bits.
    """
    bits = args.bits
    where = f"{path}: " if path is not None else ""
    if bits is None and args.white_level is not None:
        bits = max(int(math.ceil(args.white_level)).bit_length(), 1)
    if bits is None and path is not None:
        bits = png_significant_bits(path)
    if bits is None:
        bits = 8 if raw.dtype == np.uint8 else saturation_bits(raw)
    if bits is None and not required:
        bits = container_bits(raw.dtype)
    if bits is None:
        raise SveliveError(f"{where}a {8 * raw.dtype.itemsize}-bit file that does not say the sensor's bit depth "
                           f"(values up to {int(raw.max())}, none saturated at a full-scale value): pass --bits "
                           "(e.g. --bits 12) or --white-level")
    sensor = Sensor(bits=bits, black_level=0.0 if args.black_level is None else args.black_level,
                    white_level=args.white_level)
    if raw.max() > sensor.white_level:
        raise SveliveError(f"{where}the frame has values up to {int(raw.max())}, above the white level "
                           f"{sensor.white_level:g} of {bits} bits: pass the right --bits or --white-level")
    return sensor


def _progress(args: argparse.Namespace):
    """A callback printing progress lines with the elapsed time on stderr, or None with -q."""
    if args.quiet:
        return None
    start = time.monotonic()
    return lambda text: print(f"[{time.monotonic() - start:5.1f} s] {text}", file=sys.stderr, flush=True)


def _frame_files(args: argparse.Namespace) -> tuple[list[np.ndarray], list[float] | None, Camera]:
    """The raw frames given as image files, their --exposure-times and the camera the options describe."""
    if args.pattern is None:
        raise SveliveError("image frames need --pattern (the exposure tile, e.g. 1,4/16,64)")
    raws = [read_raw(p) for p in args.raw]
    sensors = [sensor_from_args(raw, args, path) for raw, path in zip(raws, args.raw)]
    if len({(s.bits, s.white_level) for s in sensors}) > 1:
        raise SveliveError("the frames imply different bit depths "
                           f"({', '.join(str(s.bits) for s in sensors)}): pass --bits")
    times = args.exposure_times
    if len(raws) > 1 and times is None:
        raise SveliveError(f"{len(raws)} frames need --exposure-times with one time per frame, e.g. "
                           f"--exposure-times {','.join(str(10000 + 5000 * i) for i in range(len(raws)))}")
    if times is not None and len(times) != len(raws):
        raise SveliveError(f"--exposure-times gives {len(times)} times for {len(raws)} frames: give one per frame")
    return raws, times, build_camera(CameraSettings.from_args(args), sensors[0])


def _recorded_sweep(args: argparse.Namespace) -> tuple[list[np.ndarray], list[float] | None, Camera]:
    """One frame per recorded exposure time of a recording (the middle one of the frames at that time;
    ``svelive record --exposure-times``), the times, and the recording's camera (--pattern, --cfa
    and the levels override it)."""
    from replay import RecordingReader

    if len(args.raw) != 1:
        raise SveliveError("give one recording (.sverec) alone, not with other frames")
    if args.exposure_times is not None:
        raise SveliveError("a recording carries its frames' exposure times: drop --exposure-times")
    with RecordingReader(args.raw[0]) as reader:
        recorded = reader.exposure_times()
        known = np.unique(recorded[np.isfinite(recorded)])
        if known.size == 0:
            raise SveliveError(f"{args.raw[0]}: the recording has no exposure times: record a sweep with "
                               "'svelive record --exposure-times T1,T2 --frames N', or give frames and --exposure-times")
        picks = [int(np.flatnonzero(recorded == t)[np.count_nonzero(recorded == t) // 2]) for t in known]
        raws = [reader.read(i).raw for i in picks]
        camera = reader.camera
    sensor = camera.sensor
    if args.bits is not None or args.black_level is not None or args.white_level is not None:
        bits = args.bits if args.bits is not None else sensor.bits
        sensor = Sensor(bits=bits, black_level=sensor.black_level if args.black_level is None else args.black_level,
                        white_level=args.white_level if args.white_level is not None else
                        (sensor.white_level if args.bits is None else None))
    cfa = args.cfa if args.cfa is not None else (camera.cfa.name if camera.cfa is not None else None)
    if parse_cfa(cfa) is None and camera.cfa is not None:  # --cfa none would read a Bayer mosaic as monochrome
        raise SveliveError(f"{args.raw[0]}: the recording's camera has the colour filter {camera.cfa.name}, but "
                           f"--cfa {args.cfa} was given: drop --cfa")
    camera = build_camera(CameraSettings(pattern=args.pattern or camera.require_pattern(), cfa=cfa), sensor)
    return raws, [float(t) for t in known] if known.size > 1 else None, camera


def _response(args: argparse.Namespace) -> int:
    check_output_target(args.output)  # before the fits, not after them
    if any(p.suffix.lower() == ".sverec" for p in args.raw):
        raws, times, camera = _recorded_sweep(args)
    else:
        raws, times, camera = _frame_files(args)
    config = ResponseFitConfig(max_degree=args.max_degree, window=args.window, refine_ratios=args.refine_ratios,
                               max_knots=args.max_knots)
    planes = [one_colour_plane(camera.check(raw), camera) for raw in raws]  # colour: one filter's pixels
    response = fit_response([p for p, _ in planes] if len(raws) > 1 else planes[0][0], planes[0][1], camera.sensor,
                            config, exposure_times=times, progress=_progress(args))
    save_response(response, args.output)
    lo, hi = response.stats["measured_range"]
    band = max(response.stats["band"]["standard_error"])
    model = f"log-spline, {len(response.knots)} knots" if response.knots else f"degree {response.degree}"
    print(f"{model}, measured brightness {lo:.3f}..{hi:.3f} (standard error up to {band:.2%} of "
          f"full scale), {response.stats['locations']} constant regions, {response.stats['equations']} equations "
          f"from {len(raws)} frame{'s' if len(raws) > 1 else ''} -> {args.output}")
    ratio = response.stats["common_ratio"]
    if ratio is not None:
        what = "frame" if len(raws) == 1 else "sweep"
        print(f"note: every exposure ratio of this {what} is a power of {ratio:g}, so it cannot tell the "
              f"curve from one with a ripple periodic in log{ratio:g}(I); the polynomial fit settles it, which "
              "suits smooth curves but can be off by a few % of full scale on S-shaped (film) curves; frames at "
              "global exposure times whose ratio is not a power of it (e.g. 1.5) remove the ambiguity "
              "(docs/calibration.md)", file=sys.stderr)
    return 0


def _mask(args: argparse.Namespace) -> int:
    check_output_target(args.output)
    flats = [read_raw(p) for p in args.flats]
    sensor = [sensor_from_args(f, args, p) for f, p in zip(flats, args.flats)][0]
    mask = estimate_mask(flats, parse_tile(args.tile), sensor, MaskConfig(vignetting_degree=args.vignetting_degree))
    save_mask(mask, args.output)
    tile = "/".join(",".join(f"{v:.4g}" for v in row) for row in mask.tile_exposures)
    print(f"tile exposures {tile}; vignetting down to {float(mask.vignetting.min()):.3f}; "
          f"per-pixel deviation {float(np.std(mask.deviation)):.2%} rms -> {args.output}")
    return 0


def _noise(args: argparse.Namespace) -> int:
    if args.output:
        check_output_target(args.output)
    frames = [read_raw(p) for p in args.frames]
    sensor = sensor_from_args(frames[0], args, args.frames[0], required=False)
    pattern = Pattern.parse(args.pattern) if args.pattern else None
    model = calibrate_noise(frames, sensor, pattern)
    data = model.to_dict()
    if args.output:
        write_json(data, args.output)
    print(json.dumps(data, indent=2))
    return 0


def _levels(p: argparse.ArgumentParser) -> None:
    add_camera_option(p, "bits", "bit depth of the raw values (default: what --white-level implies, a PNG's sBIT, "
                                 "8 for 8-bit files, or the value saturated pixels hold)")
    # no default here: a recording's own black level stands unless one is given (image files: 0)
    add_camera_option(p, "black_level", "black level, DN (default: a recording's own, else 0)", metavar="BLACK")
    add_camera_option(p, "white_level", "white level, DN (default 2^bits - 1)", metavar="WHITE")


def add_commands(sub: argparse._SubParsersAction) -> None:

    cal = sub.add_parser("calibrate", help="calibrate the response, the exposure mask or the noise from data")
    verbs = cal.add_subparsers(dest="calibration", required=True, metavar="WHAT")

    p = verbs.add_parser("response", help="camera response polynomial from SVE frames of a still scene (one, or "
                                          "several at different global exposure times)")
    p.add_argument("raw", type=existing_file, nargs="+", metavar="FRAME",
                   help="raw frame(s) (.npy, PNG, TIFF, PGM) of one still scene, or one recording (.sverec) of "
                        "a sweep ('svelive record --exposure-times'): a frame per recorded time")
    p.add_argument("--exposure-times", type=parse_times, metavar="T1,T2,...",
                   help="global exposure time of every frame, in any one unit (needed for two or more frames)")
    add_camera_option(p, "pattern", "exposure tile, e.g. 1,4/16,64, or a preset (needed for image frames; a "
                                    "recording has its own)")
    add_camera_option(p, "cfa", "colour filter layout of the frames, e.g. RGGB or quad-RGGB (default: none, "
                                "monochrome); the fit then reads one filter's pixels (green on a Bayer mosaic)")
    _levels(p)
    p.add_argument("--max-degree", type=int, default=6, help="highest polynomial degree tried (default 6)")
    p.add_argument("--window", type=int, default=3, help="local window side in tiles (odd, default 3)")
    p.add_argument("--refine-ratios", action="store_true", help="re-estimate intermediate exposure ratios")
    p.add_argument("--max-knots", type=int, default=SWEEP_KNOTS,
                   help="a sweep of two or more frames is also offered a log-spline of this many knots (and a "
                        f"power law), for film-like S-shaped responses (default {SWEEP_KNOTS}; 0: polynomials only; "
                        "docs/calibration.md)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress lines on stderr")
    p.add_argument("-o", "--output", type=Path, required=True, help="response JSON to write")
    p.set_defaults(func=_response)

    p = verbs.add_parser("mask", help="per-pixel exposure map from flat-field frames")
    p.add_argument("flats", type=existing_file, nargs="+", metavar="FLAT", help="flat-field raw frames")
    p.add_argument("--tile", required=True, help="exposure tile size HxW, e.g. 2x2")
    _levels(p)
    p.add_argument("--vignetting-degree", type=int, default=4, help="degree of the vignetting surface (default 4)")
    p.add_argument("-o", "--output", type=Path, required=True, help="mask .npz to write")
    p.set_defaults(func=_mask)

    p = verbs.add_parser("noise", help="gain and read noise from a pair of frames or one frame of a still scene")
    p.add_argument("frames", type=existing_file, nargs="+", metavar="FRAME", help="one or two raw frames")
    add_camera_option(p, "pattern", "exposure tile (needed for a single frame)")
    _levels(p)
    p.add_argument("-o", "--output", type=Path, help="noise JSON to write (also printed)")
    p.set_defaults(func=_noise)
