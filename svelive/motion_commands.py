"""CLI verb ``reconstruct-sequence``: a stream of raw SVE frames to one EXR per frame (Y, confidence, motion)."""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from svelive.capture.commands import add_source_arguments, source_from_args
from svelive.capture.images import natural_key
from svelive.errors import SveliveError
from svelive.exr import write_exr
from svelive.reconstruction.methods import METHODS
from svelive.reconstruction.stream import EXPOSURE_TIMINGS, Reconstructor


def add_commands(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("reconstruct-sequence",
                       help="reconstruct a stream of raw SVE frames with motion-robust temporal fusion, one EXR each",
                       description="Writes DIR/frame_NNNNNN.exr with channels Y (radiance, DN at exposure 1), "
                                   "confidence (0..1) and motion (1 where the pixel moved). --source also takes a "
                                   "plain directory of raw .npy (or PNG/TIFF/PGM) frames.")
    add_source_arguments(p)
    p.add_argument("--method", choices=list(METHODS), help=f"single-frame method (default: {next(iter(METHODS))})")
    p.add_argument("--timing", choices=EXPOSURE_TIMINGS, default="mask",
                   help="mask: all exposures integrate together; integration: exposures are different "
                        "integration times (turns on the within-frame consistency test)")
    p.add_argument("--gain", type=float, help="electrons per DN")
    p.add_argument("--read-noise", type=float, help="read noise, DN")
    p.add_argument("--no-temporal", action="store_true", help="no fusion across frames")
    p.add_argument("--frames", type=int, help="stop after N frames")
    p.add_argument("--half", action="store_true", help="write half floats")
    p.add_argument("-o", "--output", required=True, type=Path, help="output directory (created)")
    p.set_defaults(func=_reconstruct_sequence)


def npy_frames(directory: Path) -> Iterator[np.ndarray]:
    """The .npy raw frames of a directory in natural name order, each a 2-D uint8/uint16 array."""
    files = sorted((p for p in directory.iterdir() if p.suffix.lower() == ".npy"), key=lambda p: natural_key(str(p)))
    for path in files:
        try:
            raw = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise SveliveError(f"{path}: not a readable .npy array ({exc})") from None
        if raw.ndim != 2 or raw.dtype not in (np.uint8, np.uint16):
            raise SveliveError(f"{path}: a raw frame must be a 2-D uint8 or uint16 array, got {raw.dtype} {raw.shape}")
        yield raw


def _raw_frames(args: argparse.Namespace) -> tuple[Iterator[np.ndarray], str | None, object]:
    """(raw frames, the source's pattern or None, the source to close or None)."""
    plain = Path(args.source)
    if plain.is_dir():
        if any(p.suffix.lower() == ".npy" for p in plain.iterdir()):
            return npy_frames(plain), None, None
        args.source = f"images:{plain}"
    source = source_from_args(args)
    source.open()
    return (frame.raw for frame in source.frames()), source.pattern, source


def _reconstruct_sequence(args: argparse.Namespace) -> int:
    if args.frames is not None and args.frames < 1:
        raise SveliveError(f"--frames must be >= 1, got {args.frames}")
    frames, source_pattern, source = _raw_frames(args)
    try:
        pattern = args.pattern or source_pattern
        if not pattern:
            raise SveliveError("no exposure pattern: pass --pattern (e.g. 1,4/16,64)")
        reconstructor = Reconstructor(pattern, method=args.method, temporal=not args.no_temporal,
                                      exposure_timing=args.timing, black_level=args.black_level or 0,
                                      white_level=args.white_level, gain=args.gain, read_noise=args.read_noise)
        args.output.mkdir(parents=True, exist_ok=True)
        n = 0
        for raw in frames:
            result = reconstructor.process(raw)
            write_exr(args.output / f"frame_{n:06d}.exr",
                      {"Y": result.image, "confidence": result.confidence,
                       "motion": result.motion.astype(np.float32)},
                      {"svelive_method": result.method, "svelive_pattern": str(reconstructor.pattern),
                       "svelive_moving_fraction": f"{result.moving_fraction:.6f}"}, half=args.half)
            n += 1
            if args.frames is not None and n >= args.frames:
                break
    finally:
        if source is not None:
            source.close()
    if n == 0:
        raise SveliveError(f"{args.source}: no frames")
    print(f"{n} frames written to {args.output}")
    return 0
