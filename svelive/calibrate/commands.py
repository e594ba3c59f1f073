"""The ``svelive calibrate response|mask|noise`` verbs."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from svelive.calibrate.mask import MaskConfig, estimate_mask, parse_tile, save_mask
from svelive.calibrate.noise import estimate_noise
from svelive.calibrate.response import ResponseFitConfig, fit_response, save_response, write_json
from svelive.commands import read_raw
from svelive.errors import SveliveError
from svelive.pattern import Pattern
from svelive.sensor import Sensor, container_bits


def sensor_from_args(raw: np.ndarray, args: argparse.Namespace) -> Sensor:
    """Sensor levels from --bits/--black-level/--white-level, the bit depth defaulting to the container's."""
    bits = args.bits if args.bits is not None else container_bits(raw.dtype)
    sensor = Sensor(bits=bits, black_level=args.black, white_level=args.white)
    if raw.max() > sensor.white_level:
        raise SveliveError(f"the frame has values up to {int(raw.max())}, above the white level "
                           f"{sensor.white_level:g} of {bits} bits: pass the right --bits or --white-level")
    return sensor


def _response(args: argparse.Namespace) -> int:
    raw = read_raw(args.raw)
    sensor = sensor_from_args(raw, args)
    config = ResponseFitConfig(max_degree=args.max_degree, window=args.window, refine_ratios=args.refine_ratios)
    response = fit_response(raw, Pattern.parse(args.pattern), sensor, config)
    save_response(response, args.output)
    lo, hi = response.stats["measured_range"]
    print(f"degree {response.degree}, measured brightness {lo:.3f}..{hi:.3f}, "
          f"{response.stats['locations']} constant regions -> {args.output}")
    ratio = response.stats["common_ratio"]
    if ratio is not None:
        print(f"note: every exposure ratio of this pattern is a power of {ratio:g}, so the frame cannot tell the "
              f"curve from one with a ripple periodic in log{ratio:g}(I); the polynomial fit settles it, which "
              "suits smooth curves but can be off by a few % of full scale on S-shaped (film) curves "
              "(docs/calibration.md)", file=sys.stderr)
    return 0


def _mask(args: argparse.Namespace) -> int:
    flats = [read_raw(p) for p in args.flats]
    sensor = [sensor_from_args(f, args) for f in flats][0]
    mask = estimate_mask(flats, parse_tile(args.tile), sensor, MaskConfig(vignetting_degree=args.vignetting_degree))
    save_mask(mask, args.output)
    tile = "/".join(",".join(f"{v:.4g}" for v in row) for row in mask.tile_exposures)
    print(f"tile exposures {tile}; vignetting down to {float(mask.vignetting.min()):.3f}; "
          f"per-pixel deviation {float(np.std(mask.deviation)):.2%} rms -> {args.output}")
    return 0


def _noise(args: argparse.Namespace) -> int:
    frames = [read_raw(p) for p in args.frames]
    sensor = sensor_from_args(frames[0], args)
    pattern = Pattern.parse(args.pattern) if args.pattern else None
    model = estimate_noise(frames, sensor, pattern)
    data = model.to_dict()
    if args.output:
        write_json(data, args.output)
    print(json.dumps(data, indent=2))
    return 0


def _levels(p: argparse.ArgumentParser) -> None:
    p.add_argument("--bits", type=int, help="bit depth of the raw values (default: 8 or 16 by file)")
    p.add_argument("--black-level", dest="black", type=float, default=0.0, help="black level, DN (default 0)")
    p.add_argument("--white-level", dest="white", type=float, help="white level, DN (default 2^bits - 1)")


def add_commands(sub: argparse._SubParsersAction) -> None:
    from svelive.cli import existing_file

    cal = sub.add_parser("calibrate", help="calibrate the response, the exposure mask or the noise from data")
    verbs = cal.add_subparsers(dest="calibration", required=True, metavar="WHAT")

    p = verbs.add_parser("response", help="camera response polynomial from one SVE frame of a still scene")
    p.add_argument("raw", type=existing_file, metavar="RAW", help="raw frame (.npy, PNG, TIFF, PGM)")
    p.add_argument("--pattern", required=True, help="exposure tile, e.g. 1,4/16,64, or a preset")
    _levels(p)
    p.add_argument("--max-degree", type=int, default=6, help="highest polynomial degree tried (default 6)")
    p.add_argument("--window", type=int, default=3, help="local window side in tiles (odd, default 3)")
    p.add_argument("--refine-ratios", action="store_true", help="re-estimate intermediate exposure ratios")
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
    p.add_argument("--pattern", help="exposure tile (needed for a single frame)")
    _levels(p)
    p.add_argument("-o", "--output", type=Path, help="noise JSON to write (also printed)")
    p.set_defaults(func=_noise)
