"""Core verbs of the svelive command: info, methods, simulate, reconstruct, demo."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import cv2
import numpy as np

from svelive import __version__ as svelive_version

# the demo verb's layouts are the demo camera's: dual-ISO exposures on RGGB, or mono 1,4/16,64
from svelive.capture.demo import COLOUR_PATTERN as DEMO_COLOUR_PATTERN
from svelive.capture.demo import DEFAULT_CFA as DEMO_CFA
from svelive.capture.demo import MONO_PATTERN as DEMO_MONO_PATTERN  # noqa: E402
from svelive.capture.images import decode_image
from svelive.core.atomic import check_output_target, write_bytes_atomic
from svelive.core.camera import COLOUR_LAYOUTS
from svelive.core.cfa import PRESETS as CFA_PRESETS
from svelive.core.errors import SveliveError
from svelive.core.pattern import (
    PAPER_DR_DB,
    PAPER_Q,
    PRESETS,
    Pattern,
    check_depth,
    dynamic_range_db,
    dynamic_range_stops,
    unique_levels,
)
from svelive.core.sensor import Sensor, container_bits
from svelive.exr import LUMA_WEIGHTS, compress_on, image_channels, read_luminance, read_rgb, write_exr
from svelive.frame_exr import FrameInfo, single_frame_balance, write_frame_exr
from svelive.noise import PRIOR_LOG_SIGMA, NoiseEstimate
from svelive.options import CameraSettings, add_camera_option, build_camera, parse_cfa
from svelive.reconstruction.input import prepare, with_noise_model
from svelive.reconstruction.single import methods, reconstruct
from svelive.simulation import SAMPLE_SCENES, exposure_scale, load_sample_scene, simulate
from svelive.whitebalance import OUTPUT_SPACES, ColourSettings

RAW_SUFFIXES = (".png", ".tif", ".tiff", ".pgm", ".npy")
#: The ``units`` attribute of a simulation's ground truth (the radiance the reconstruction estimates).
TRUTH_UNITS = "radiance, DN at relative exposure 1 (simulation ground truth)"


def add_commands(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("info", help="dynamic range and quantisation levels of a pattern (paper sections 4-5)")
    add_camera_option(p, "pattern", "exposure tile, e.g. '1,4/16,64', or a preset: " + ", ".join(PRESETS),
                      required=True)
    add_camera_option(p, "bits", "bit depth of the raw values (default 12, the simulated sensor's; 8 compares "
                                 "with the paper's figures)", default=12)
    p.set_defaults(func=_info)

    p = sub.add_parser("methods", help="list the reconstruction methods, the default first")
    p.set_defaults(func=_methods)

    p = sub.add_parser("simulate", help="render a raw SVE frame from a linear HDR EXR image")
    p.add_argument("hdr", help="linear HDR EXR (luminance from Y or R, G, B; with --cfa its R, G, B)")
    _add_pattern_sensor(p, bits_default=12)
    add_cfa_argument(p, "colour filter the scene is seen through, e.g. RGGB (default: none, a monochrome "
                        "sensor seeing the luminance)")
    p.add_argument("--full-well", type=float, default=10_000.0, help="full-well capacity, electrons")
    p.add_argument("--read-noise-e", type=float, default=3.0, help="read noise, electrons")
    p.add_argument("--stops-below-fill", type=float, default=0.0,
                   help="0: the scene's brightest point just fills the lowest exposure; each stop halves the light")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--truth", type=Path, help="also write the ground truth (DN at exposure 1; RGB with --cfa) "
                                              "to this EXR")
    p.add_argument("-o", "--output", type=Path, required=True, help="raw frame: .png, .tif, .pgm or .npy")
    p.set_defaults(func=_simulate)

    p = sub.add_parser("reconstruct", help="reconstruct an HDR EXR from one raw SVE frame")
    p.add_argument("raw", type=Path, help="8/16-bit single-channel PNG, TIFF, PGM or .npy")
    _add_pattern_sensor(p, bits_default=None)
    add_cfa_argument(p, "colour filter of the sensor, e.g. RGGB: writes an RGB EXR (default: none, or the "
                        "layout's)")
    p.add_argument("--gain", type=float, help="electrons per DN (noise-aware methods)")
    p.add_argument("--read-noise", type=float, help="read noise in DN (noise-aware methods)")
    p.add_argument("--response", type=Path, help="response JSON (svelive calibrate response): linearise first")
    p.add_argument("--mask", type=Path, help="mask .npz (svelive calibrate mask): per-pixel exposures")
    p.add_argument("--method", choices=methods(), help=f"default: {methods()[0]}")
    p.add_argument("--confidence", action="store_true", help="also write a 'confidence' channel")
    p.add_argument("--half", action="store_true", help="write half floats instead of float32")
    p.add_argument("-v", "--verbose", action="store_true",
                   help="print the noise model used (given, or estimated from the frame with its uncertainty)")
    add_colour_arguments(p)
    p.add_argument("-o", "--output", type=Path, required=True, help="output .exr")
    p.set_defaults(func=_reconstruct)

    p = sub.add_parser("demo", help="simulate and reconstruct a shipped sample scene, print its dynamic range")
    p.add_argument("--scene", choices=SAMPLE_SCENES, default="desk")
    add_cfa_argument(p, f"colour filter (default {DEMO_CFA}; 'none': a monochrome sensor)")
    add_camera_option(p, "pattern", f"exposure pattern (default {DEMO_COLOUR_PATTERN} in colour, the dual-ISO "
                                    f"layout; {DEMO_MONO_PATTERN} in mono)")
    p.add_argument("--method", choices=methods())
    add_colour_arguments(p)
    p.add_argument("-o", "--output", type=Path, default=Path("svelive-demo.exr"))
    p.set_defaults(func=_demo)


def add_cfa_argument(p: argparse.ArgumentParser, text: str) -> None:
    """The --cfa option of the verbs that read or make raw frames."""
    add_camera_option(p, "cfa", f"{text}; presets: {', '.join(CFA_PRESETS)}, or rows such as R,G/G,B")


def add_colour_arguments(p: argparse.ArgumentParser) -> None:
    """How a colour result is written: white balance, camera -> Rec.709 matrix, output space."""
    p.add_argument("--white-balance", default="auto", metavar="auto|R,G,B",
                   help="colour: 'auto' (grey world over the well-exposed pixels; default) or fixed multipliers "
                        "R,G,B; recorded in the EXR, applied only with --output-space rec709")
    p.add_argument("--colour-matrix", metavar="9 NUMBERS",
                   help="colour: 3x3 matrix from white-balanced camera RGB to linear Rec.709, row-major, "
                        "comma-separated (write --colour-matrix=... when the first number is negative)")
    p.add_argument("--output-space", choices=OUTPUT_SPACES, default="camera",
                   help="colour: camera RGB as reconstructed (default) or Rec.709 (white balance and matrix applied)")


def colour_settings(args: argparse.Namespace) -> ColourSettings:
    """The colour output the command line asks for."""
    return ColourSettings(args.white_balance, args.colour_matrix, args.output_space)


def luminance(image: np.ndarray) -> np.ndarray:
    """float32 (H, W): the image itself, or the Rec. 709 luminance of an (H, W, 3) one."""
    return image if image.ndim == 2 else (image @ np.float32(LUMA_WEIGHTS)).astype(np.float32)


def _add_pattern_sensor(p: argparse.ArgumentParser, bits_default: int | None) -> None:
    add_camera_option(p, "pattern", "exposure tile, e.g. '1,4/16,64', a preset, or a colour layout "
                                    f"({', '.join(COLOUR_LAYOUTS)}: sets --cfa too)", required=True)
    add_camera_option(p, "bits", "bit depth" + (f" (default {bits_default})" if bits_default
                                                else " (default: from the file's dtype)"), default=bits_default)
    add_camera_option(p, "black_level", "DN (default 0)", default=0.0)
    add_camera_option(p, "white_level", "DN at or above which a pixel is saturated (default 2^bits - 1)")


def _info(args: argparse.Namespace) -> int:
    pattern = Pattern.parse(args.pattern)
    if not 1 <= args.bits <= 16:
        raise SveliveError(f"--bits must be 1..16, got {args.bits}")
    print(f"pattern            {pattern}  ({len(pattern.levels)} exposures, ratio {pattern.ratio:g}), "
          f"{args.bits}-bit readings")
    print(f"detector range     {20 * math.log10(2**args.bits - 1):.2f} dB for {args.bits} bits")
    print(f"SVE dynamic range  {dynamic_range_db(pattern, args.bits):.2f} dB = "
          f"{dynamic_range_stops(pattern, args.bits):.2f} stops (paper eq. 3)")
    try:
        levels = f"{unique_levels(pattern, args.bits)} (exact enumeration of the union of every exposure's levels)"
    except SveliveError as exc:
        levels = f"not counted: {exc}"
    print(f"unique levels Q    {levels}")
    if args.bits == 8 and _is_paper_case(pattern):
        print(f"paper's figures    {PAPER_DR_DB} dB and Q = {PAPER_Q} for 8 bits, 4 exposures, ratio 4")
        print(f"note               enumeration gives Q = {unique_levels(pattern, 8)}, not {PAPER_Q}: "
              f"256 levels of the highest exposure plus 192 new levels from each lower one (levels q/e that "
              f"coincide count once); the paper's eq. 4 is garbled in the available text and its 869 "
              f"could not be reproduced (see docs/methods.md)")
    return 0


def _is_paper_case(pattern: Pattern) -> bool:
    """True for the paper's example: four exposures, each 4 times the last."""
    levels = pattern.levels / pattern.levels[0]
    return levels.size == 4 and bool(np.allclose(levels, [1, 4, 16, 64]))


def _methods(args: argparse.Namespace) -> int:
    for i, name in enumerate(methods()):
        print(f"{name}{'  (default)' if i == 0 else ''}")
    return 0


def read_raw(path: Path) -> np.ndarray:
    """A mono 8/16-bit raw frame from PNG, TIFF, PGM or .npy, uint8 or uint16 (H, W)."""
    if not path.exists():
        raise SveliveError(f"{path}: no such file")
    if not path.is_file():
        raise SveliveError(f"{path}: not a file")
    suffix = path.suffix.lower()
    if suffix not in RAW_SUFFIXES:
        raise SveliveError(f"{path}: unsupported raw format {suffix or '(none)'}; use {', '.join(RAW_SUFFIXES)}")
    if suffix == ".npy":
        try:
            raw = np.load(path, allow_pickle=False)
        except (ValueError, OSError, EOFError) as exc:
            raise SveliveError(f"{path}: not a readable .npy array ({exc})") from None
    else:
        raw = decode_image(path, suffix[1:].upper())
    if raw.ndim == 3 and raw.shape[2] == 1:
        raw = raw[:, :, 0]
    if raw.ndim != 2:
        kind = "a 3-channel (already demosaiced) image" if raw.ndim == 3 and raw.shape[2] in (3, 4) else "not a 2-D frame"
        raise SveliveError(f"{path}: expected a single-channel raw mosaic, got shape {raw.shape}: {kind}; give "
                           "the sensor's raw frame, one value per pixel (--cfa describes its colour filter)")
    if raw.dtype not in (np.uint8, np.uint16):
        raise SveliveError(f"{path}: raw values must be 8- or 16-bit unsigned integers, got {raw.dtype}")
    return raw


def png_with_sbit(png: bytes, bits: int) -> bytes:
    """``png`` (an encoded single-channel PNG) with an sBIT chunk saying ``bits`` significant bits.

    OpenCV's PNG writer cannot set sBIT, so the chunk (length, type, one byte for a grey
    image, CRC-32 of type and data) goes right after IHDR, where the PNG specification wants it
    (before PLTE and IDAT); an sBIT the file already has is replaced.
    """
    import struct
    import zlib

    signature, ihdr_end = png[:8], 8 + 8 + 13 + 4
    if signature != b"\x89PNG\r\n\x1a\n" or png[12:16] != b"IHDR":
        raise SveliveError("not a PNG stream: cannot add its sBIT chunk")
    depth, colour_type = png[24], png[25]
    if colour_type != 0 or not 1 <= bits <= depth:
        raise SveliveError(f"sBIT: {bits} significant bits do not fit a {depth}-bit "
                           f"{'grey' if colour_type == 0 else 'colour'} PNG; give 1..{depth} bits of a grey frame")
    chunk = struct.pack(">I4sB", 1, b"sBIT", bits)
    chunk += struct.pack(">I", zlib.crc32(chunk[4:]) & 0xFFFFFFFF)
    rest, pos = bytearray(), ihdr_end
    while pos < len(png):  # drop an existing sBIT (OpenCV writes none; a future version might)
        length, kind = struct.unpack(">I4s", png[pos:pos + 8])
        end = pos + 12 + length
        if kind != b"sBIT":
            rest += png[pos:end]
        pos = end
    return png[:ihdr_end] + chunk + bytes(rest)


def write_raw(path: Path, raw: np.ndarray, bits: int | None = None) -> None:
    """Write a raw frame (uint8/uint16 (H, W)) as PNG, TIFF, PGM or .npy, atomically.

    ``bits``: the sensor's bit depth (e.g. 12 for a 12-bit frame in a 16-bit file), recorded in
    a PNG's sBIT chunk so that ``svelive calibrate`` reads it back; other formats ignore it.
    """
    suffix = path.suffix.lower()
    if suffix not in RAW_SUFFIXES:
        raise SveliveError(f"{path}: unsupported raw format {suffix or '(none)'}; use {', '.join(RAW_SUFFIXES)}")
    if suffix == ".npy":
        import io

        buffer = io.BytesIO()
        np.save(buffer, raw, allow_pickle=False)
        data = buffer.getvalue()
    else:
        ok, encoded = cv2.imencode(suffix, raw)
        if not ok:
            raise SveliveError(f"{path}: could not encode the frame as {suffix[1:].upper()}")
        data = encoded.tobytes()
        if suffix == ".png" and bits is not None:
            try:
                data = png_with_sbit(data, bits)
            except SveliveError as exc:
                raise SveliveError(f"{path}: {exc}") from None
    write_bytes_atomic(path, data)


def _sensor_from_args(args: argparse.Namespace, raw: np.ndarray | None = None) -> Sensor:
    bits = args.bits if args.bits is not None else (8 if raw is None else container_bits(raw.dtype))
    return Sensor(bits=bits, black_level=args.black_level, white_level=args.white_level,
                  gain=getattr(args, "gain", None), read_noise=getattr(args, "read_noise", None))


def _simulate(args: argparse.Namespace) -> int:
    check_outputs(args.output, args.truth)
    camera = build_camera(CameraSettings.from_args(args))
    pattern = camera.require_pattern()
    if not args.hdr or not Path(args.hdr).is_file():
        raise SveliveError(f"{args.hdr}: no such EXR file")
    nominal = _sensor_from_args(args)
    check_depth(pattern, nominal.bits)
    sensor = Sensor.from_full_well(nominal.bits, args.full_well, args.read_noise_e, nominal.black_level,
                                   nominal.white_level)
    scene = np.maximum(read_luminance(args.hdr) if camera.cfa is None else read_rgb(args.hdr), 0)
    radiance = scene * exposure_scale(scene, pattern, sensor, stops_below_fill=args.stops_below_fill)
    frame = simulate(radiance, pattern, sensor, cfa=camera.cfa, seed=args.seed)
    write_raw(args.output, frame.raw, bits=sensor.bits)
    if args.truth:
        attributes = {"svelive": svelive_version, "units": TRUTH_UNITS, "pattern": str(pattern)}
        if camera.cfa is not None:
            attributes.update(cfa=camera.cfa.name, colourSpace="camera")
        write_exr(args.truth, image_channels(frame.truth), attributes)
    colour = "" if camera.cfa is None else f", colour filter {camera.cfa.name}"
    print(f"wrote {args.output} ({frame.raw.shape[1]}x{frame.raw.shape[0]}, {sensor.bits}-bit{colour}, "
          f"gain {sensor.gain:.3g} e-/DN, read noise {sensor.read_noise:.3g} DN)")
    return 0


def _reconstruct(args: argparse.Namespace) -> int:
    check_outputs(args.output)
    compress_on()  # the output's compression on every core
    camera = build_camera(CameraSettings.from_args(args))
    settings = colour_settings(args)
    raw = read_raw(args.raw)
    sensor = _sensor_from_args(args, raw)
    if raw.dtype == np.uint8 and sensor.bits > 8:
        raise SveliveError(f"{args.raw}: 8-bit file but --bits {sensor.bits}")
    th, tw = camera.period
    if raw.shape[0] < th or raw.shape[1] < tw:
        raise SveliveError(f"{args.raw}: frame {raw.shape[1]}x{raw.shape[0]} is smaller than the {tw}x{th} tile")
    pattern = camera.require_pattern()
    if args.mask:
        from svelive.calibrate import load_mask
        pattern = pattern.with_pixel_map(load_mask(args.mask))
    check_depth(pattern, sensor.bits)
    response = None
    if args.response:
        from svelive.calibrate import load_response
        response = load_response(args.response)
    # one camera: the input preparation applies the response and the per-pixel map (svelive.reconstruction.input)
    camera = camera.replace(pattern=pattern, sensor=sensor, response=response)
    method = args.method or methods()[0]
    # the noise model: given, or estimated from this frame once (and named in the EXR and with -v)
    noise = with_noise_model(raw, camera, prepare(raw, camera))[2]
    image, confidence = reconstruct(raw, camera, method=args.method, noise=noise, return_confidence=True)
    write_frame_exr(args.output, image, FrameInfo(camera, method, attributes=noise.attributes()), settings,
                    single_frame_balance(image, settings, confidence > 0),
                    {"confidence": confidence} if args.confidence else None, half=args.half)
    kind = "" if camera.cfa is None else f", RGB ({settings.output_space})"
    print(f"wrote {args.output} ({image.shape[1]}x{image.shape[0]}{kind}, method {method})")
    if args.verbose:
        print(explain_noise(noise, sensor))
    return 0


def check_outputs(*paths: Path | None) -> None:
    """Refuse an output that cannot be written (a FIFO, link, directory, missing folder) before any work."""
    for path in paths:
        if path is not None:
            check_output_target(path)


def explain_noise(noise: NoiseEstimate, sensor: Sensor) -> str:
    """One line for ``reconstruct -v``: each of gain and read noise given, estimated from the frame (with its
    uncertainty), or a default the frame could not tell (and the option that gives it)."""
    if noise.source == "given":
        return noise.describe()
    parts = [_noise_part("gain", noise.gain, noise.gain_sigma, "e-/DN", sensor.gain, "--gain", noise.source),
             _noise_part("read noise", noise.read_noise, noise.read_noise_sigma, "DN", sensor.read_noise,
                         "--read-noise", noise.source)]
    return f"noise ({noise.source}): {'; '.join(parts)} ({noise.samples} noise samples in the frame)"


def _noise_part(name: str, value: float, sigma: float | None, unit: str, given: float | None, option: str,
                source: str) -> str:
    if given is not None:
        return f"{name} {value:.4g} {unit} as given"
    prior_only = sigma is None or math.isclose(sigma, PRIOR_LOG_SIGMA * value, rel_tol=1e-9)
    if source == "estimated" and not prior_only:
        return f"{name} {value:.4g} +- {sigma:.3g} {unit} estimated from the frame"
    return f"{name} {value:.4g} {unit} is the default: the frame's noise samples could not tell it; give {option}"


def _demo(args: argparse.Namespace) -> int:
    check_outputs(args.output)
    cfa = args.cfa if args.cfa is not None else DEMO_CFA
    pattern = args.pattern or (DEMO_MONO_PATTERN if parse_cfa(cfa) is None else DEMO_COLOUR_PATTERN)
    camera = build_camera(CameraSettings(pattern, cfa), Sensor.from_full_well(12, 10_000, 3))
    pattern, sensor = camera.require_pattern(), camera.sensor
    check_depth(pattern, sensor.bits)
    settings = colour_settings(args)
    scene = np.maximum(load_sample_scene(args.scene, rgb=camera.cfa is not None), 0)
    frame = simulate(scene * exposure_scale(scene, pattern, sensor), pattern, sensor, cfa=camera.cfa, seed=0)
    method = args.method or methods()[0]
    image, confidence = reconstruct(frame.raw, camera, method=method, return_confidence=True)
    balance = single_frame_balance(image, settings, confidence > 0)
    write_frame_exr(args.output, image, FrameInfo(camera, method), settings, balance, {"confidence": confidence})
    measured = luminance(image)[confidence > 0.5]
    low, high = np.percentile(measured, [0.1, 99.9]) if measured.size else (0.0, 0.0)
    kind = "" if camera.cfa is None else f" {camera.cfa.name} colour"
    print(f"scene {args.scene}: {frame.raw.shape[1]}x{frame.raw.shape[0]} 12-bit{kind} SVE frame, pattern {pattern}, "
          f"method {method}")
    print(f"sensor range: one exposure {20 * math.log10(sensor.range_dn):.1f} dB, "
          f"SVE {dynamic_range_db(pattern, 12):.1f} dB (theory)")
    if low > 0:
        print(f"reconstructed dynamic range (0.1-99.9 percentile of luminance, confidence > 0.5): "
              f"{20 * math.log10(high / low):.1f} dB = {math.log2(high / low):.1f} stops")
    if balance is not None:
        red, _, blue = np.float32(balance.multipliers)  # as the EXR stores them
        print(f"white balance ({balance.mode}): R {red:.3f}, G 1, B {blue:.3f}; "
              f"EXR in {settings.output_space} RGB")
    print(f"wrote {args.output}")
    return 0
