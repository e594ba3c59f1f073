"""CLI verb ``reconstruct-sequence``: a stream of raw SVE frames to one EXR per frame (Y or R, G, B, confidence, motion).

Every frame is reconstructed with its own camera (svelive.Camera: pattern, colour filter,
sensor, response), as the source attached it: a replayed Bayer recording comes out in colour,
linearised through the response it was recorded with.

The frames are reconstructed and written by svelive.reprocess, which writes every EXR the same
way (svelive.frame_exr): a recording (``--source replay:FILE``) by frame index, in this process
or with ``--workers N`` / ``--scheduler tcp://HOST:8786`` on a Dask cluster, its EXRs named by
the frame's index in the recording, a second run skipping the complete ones; any other source in
order (svelive.reprocess.run_stream). This module turns the options into those calls.
"""

from __future__ import annotations

import argparse
import sys
from collections import deque
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from svelive.capture.images import natural_key
from svelive.cli import print_json
from svelive.cli.capture import add_source_arguments, parse_opts, source_from_args
from svelive.cli.reconstruct import add_colour_arguments, colour_settings
from svelive.core.camera import Camera, camera_for_raw
from svelive.core.errors import SveliveError
from svelive.core.frame import Frame
from svelive.exr import compress_on
from svelive.memory import keep_freed_memory
from svelive.noise import NoiseEstimate
from svelive.options import CameraSettings, build_camera
from svelive.progress import Progress, add_quiet_argument
from svelive.reconstruction.methods import METHODS
from svelive.reconstruction.stream import EXPOSURE_TIMINGS, NOISE_FRAMES, default_method, stream_noise
from svelive.reprocess import require_dask, run_stream


def add_commands(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("reconstruct-sequence",
                       help="reconstruct a stream of raw SVE frames with motion-robust temporal fusion, one EXR each",
                       description="Writes DIR/frame_NNNNNN.exr with channels Y (radiance, DN at exposure 1), or "
                                   "R, G, B for a colour camera, confidence (0..1) and motion (1 where the pixel "
                                   "moved). Each frame is reconstructed with its own camera (a recording's "
                                   "pattern, colour filter, sensor and response; --pattern, --bits, --black-level "
                                   "and --white-level replace the recorded ones). --source also takes a "
                                   "plain directory of raw .npy (or PNG/TIFF/PGM) frames. A recording "
                                   "(replay:FILE) is read by frame index, NNNNNN is the frame's index in it, a "
                                   "damaged frame is skipped, and a second run skips the complete EXRs; "
                                   "--workers/--scheduler spread it over a Dask cluster (docs/reprocessing.md).")
    add_source_arguments(p)
    p.add_argument("--method", choices=list(METHODS),
                   help=f"single-frame method (default: {default_method(True)} with temporal fusion, "
                        f"{default_method(False)} with --no-temporal)")
    p.add_argument("--timing", choices=EXPOSURE_TIMINGS, default="mask",
                   help="mask: all exposures integrate together; integration: exposures are different "
                        "integration times (turns on the within-frame consistency test)")
    p.add_argument("--gain", type=float, help="electrons per DN")
    p.add_argument("--read-noise", type=float, help="read noise, DN")
    p.add_argument("--no-temporal", action="store_true", help="no fusion across frames")
    p.add_argument("--frames", type=int, help="stop after N frames")
    p.add_argument("--half", action="store_true", help="write half floats")
    cluster = p.add_argument_group("reprocessing a recording on a Dask cluster (replay: sources)")
    cluster.add_argument("--workers", type=int, metavar="N",
                         help="reconstruct on a local Dask cluster of N worker processes (one thread each)")
    cluster.add_argument("--scheduler", metavar="tcp://HOST:8786",
                         help="use this running Dask scheduler instead of a local cluster (its workers must "
                              "see the recording and the output directory at the same paths)")
    cluster.add_argument("--warmup", type=int, metavar="K",
                         help="frames a temporal chunk runs before its first frame (default: until the fused "
                              "history agrees with the sequential run's to float32 rounding, 133 frames)")
    cluster.add_argument("--tolerance", type=float, default=0.0, metavar="FRACTION",
                         help="fraction of a chunk's pixels whose fused state at its first frame may differ from "
                              "the run before it (another reset decision); default 0: a chunk that differs is "
                              "run again with a longer warm-up, so the result is the sequential one")
    add_quiet_argument(p)
    add_colour_arguments(p)
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


def _raw_frames(args: argparse.Namespace) -> tuple[Iterator[np.ndarray | Frame], object]:
    """(frames: Frames with their camera, or bare raw arrays of a .npy directory; the source to close or None)."""
    plain = Path(args.source)
    if plain.is_dir():
        if any(p.suffix.lower() == ".npy" for p in plain.iterdir()):
            return npy_frames(plain), None
        args.source = f"images:{plain}"
    source = source_from_args(args)
    source.open()
    return source.frames(), source


def camera_of(frame: np.ndarray | Frame, args: argparse.Namespace) -> Camera:
    """The camera to reconstruct ``frame`` with: its own (a bare array's from the options), with --gain and
    --read-noise when given."""
    if isinstance(frame, Frame):
        camera = frame.camera
    else:
        given = CameraSettings.from_args(args)
        sensor = camera_for_raw(frame, None, black_level=given.black_level or 0, white_level=given.white_level,
                                bits=given.bits).sensor
        camera = build_camera(given, sensor)  # --cfa none with a colour layout refused, as every verb does
    camera.require_pattern()
    if args.gain is not None or args.read_noise is not None:
        camera = camera.replace(sensor=camera.sensor.with_noise(args.gain, args.read_noise))
    return camera


def with_cameras(frames: Iterable[np.ndarray | Frame],
                 args: argparse.Namespace) -> Iterator[tuple[np.ndarray | Frame, Camera, NoiseEstimate]]:
    """(frame, the camera to reconstruct it with, its noise model) for every frame, in order.

    Where a camera (:func:`camera_of`) gives no gain or read noise, the model is estimated from its
    first NOISE_FRAMES frames (:func:`svelive.reconstruction.stream.stream_noise`: the frames are read
    ahead) and kept for as long as the camera stays the same; a new camera gets its own estimate.
    """
    frames = iter(frames)
    ahead: deque[np.ndarray | Frame] = deque()
    base: Camera | None = None
    camera, noise = None, None
    while True:
        frame = ahead.popleft() if ahead else next(frames, None)
        if frame is None:
            return
        own = camera_of(frame, args)
        if own != base:
            while len(ahead) < NOISE_FRAMES - 1 and (more := next(frames, None)) is not None:
                ahead.append(more)
            run = [frame]
            for later in ahead:
                if camera_of(later, args) != own:
                    break
                run.append(later)
            base, noise = own, stream_noise(run, own, method=args.method, exposure_timing=args.timing)
            camera = own.replace(sensor=noise.apply(own.sensor))
        yield frame, camera, noise


def _say(noise: NoiseEstimate) -> None:
    """The noise model estimated from a stream's first frames, one line on stderr."""
    print(f"{noise.describe()}, from the first {NOISE_FRAMES} frames at most", file=sys.stderr)


def _reconstruct_sequence(args: argparse.Namespace) -> int:
    if args.frames is not None and args.frames < 1:
        raise SveliveError(f"--frames must be >= 1, got {args.frames}")
    if args.workers is not None and not 1 <= args.workers <= 256:
        raise SveliveError(f"--workers must be 1..256, got {args.workers}")
    if not 0 <= args.tolerance < 1:
        raise SveliveError(f"--tolerance is a fraction of the pixels, 0 <= F < 1, got {args.tolerance}")
    if args.workers is not None or args.scheduler is not None:
        require_dask()  # before any work (it was said after the stream's noise estimate)
    settings = colour_settings(args)
    compress_on()  # this process's EXRs compressed on every core (Dask's workers keep one thread each)
    if args.source.strip().lower().startswith("replay:"):
        return _reprocess(args, settings)
    if args.workers is not None or args.scheduler is not None or args.warmup is not None or args.tolerance:
        raise SveliveError("--workers, --scheduler, --warmup and --tolerance reprocess a recording: give --source "
                           "replay:FILE (record other sources first with svelive record)")
    frames, source = _raw_frames(args)
    keep_freed_memory()  # frame buffers reused from frame to frame

    def new_stream(noise: NoiseEstimate) -> None:
        if noise.source != "given" and not args.quiet:
            _say(noise)

    try:
        with Progress("reconstructing", total=args.frames, quiet=args.quiet) as progress:
            n = run_stream(with_cameras(frames, args), args.output, method=args.method, temporal=not args.no_temporal,
                           timing=args.timing, colour=settings, half=args.half, limit=args.frames,
                           on_frame=lambda _: progress.update(), on_camera=new_stream)
    finally:
        if source is not None:
            source.close()
    if n == 0:
        raise SveliveError(f"{args.source}: no frames")
    print(f"{n} frames written to {args.output}")
    return 0


def _reprocess(args: argparse.Namespace, settings: object) -> int:
    """``--source replay:FILE``: svelive.reprocess, in this process or on Dask."""
    from svelive import reprocess
    from svelive.capture import parse_spec

    _, path = parse_spec(args.source)
    options = {**CameraSettings.from_args(args).source_options(), **parse_opts(args.opt)}
    job = reprocess.Job(recording=str(Path(path).resolve()), output=str(args.output.resolve()), method=args.method,
                        temporal=not args.no_temporal, timing=args.timing,
                        source_options={k: v for k, v in options.items() if v is not None},
                        gain=args.gain, read_noise=args.read_noise, colour=settings, half=args.half,
                        frames=args.frames)
    if args.output.exists() and not args.output.is_dir():
        raise SveliveError(f"{args.output}: exists and is not a folder")
    reprocess.frame_count(job)  # a bad recording or option fails here, in one line, before any cluster starts
    job = reprocess.with_stream_noise(job)
    if job.noise is not None and not args.quiet:
        _say(job.noise)
    with Progress("reconstructing", quiet=args.quiet) as progress:
        if args.workers is None and args.scheduler is None:
            summary = reprocess.run_local(job, progress, args.warmup, args.tolerance)
        else:
            workers = args.workers or 1
            client = reprocess.connect(workers, args.scheduler)
            try:
                if args.scheduler:
                    workers = max(1, len(client.scheduler_info().get("workers", {})))
                summary = reprocess.run_dask(job, client, workers, progress, args.warmup, tolerance=args.tolerance)
            finally:
                cluster = getattr(client, "cluster", None)
                client.close()
                if cluster is not None and args.scheduler is None:
                    cluster.close()
    if summary.written + summary.complete == 0:
        raise SveliveError(f"{args.source}: no intact frames")
    print_json({"output": str(args.output), **summary.to_dict()})
    return 0
