"""CLI verbs of the capture layer: ``record``, ``replay-info``, ``export``.

Import from an image sequence is ``svelive record --source images:DIR -o OUT``:
every source records the same way.
"""

from __future__ import annotations

import argparse
import queue
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any, Iterator

from replay import CorruptFrameError, RecordingReader, RecordingWriter, WriterConfig
from replay.reader import _ranges, report
from svelive.capture import AfterChange, open_source
from svelive.cli import parse_times, print_json
from svelive.core.errors import SveliveError
from svelive.core.frame import Frame
from svelive.options import SOURCE_CFA_HELP, CameraSettings, add_camera_option
from svelive.progress import Progress, add_quiet_argument


def add_commands(sub: argparse._SubParsersAction) -> None:
    """Add the capture verbs to the ``svelive`` parser."""

    p = sub.add_parser("record", help="record raw frames from a source into a crash-safe recording",
                       description="Record raw frames losslessly with pattern, sensor metadata and timestamps. "
                                   "Import an image sequence with --source images:DIR.")
    add_source_arguments(p)
    p.add_argument("-o", "--output", required=True, type=Path, help="recording file to create (.sverec)")
    limit = p.add_mutually_exclusive_group()
    limit.add_argument("--frames", type=int, help="stop after N frames")
    limit.add_argument("--seconds", type=float, help="stop after S seconds")
    p.add_argument("--exposure-times", type=parse_times, metavar="T1,T2,...",
                   help="step the camera's global exposure time through these (its unit, GigE: us) and record "
                        "--frames frames at each, every frame tagged with the time the camera applied; the "
                        "exposure is put back afterwards (for `svelive calibrate response` or a replayed sweep)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing recording")
    p.add_argument("--sync-every", type=int, default=0, metavar="N",
                   help="fdatasync every N frames (survives power loss; default 0: only a process kill)")
    p.add_argument("--queue", type=int, default=64, metavar="N",
                   help="frames buffered between capture and disk before frames are dropped (default 64)")
    add_quiet_argument(p)
    p.set_defaults(func=_record)

    p = sub.add_parser("replay-info", help="print a recording's summary as JSON",
                       description="Prints the header, frame count, timing and the problems found, reading "
                                   "every frame to check its checksums: damaged_records lists every frame that "
                                   "export and reconstruct would skip (a damaged record header or damaged data). "
                                   "--no-verify: the header and index only; --verify: exit status 1 when a frame "
                                   "is damaged.")
    p.add_argument("path", type=Path)
    check = p.add_mutually_exclusive_group()
    check.add_argument("--verify", action="store_true", help="exit status 1 when a frame is damaged")
    check.add_argument("--no-verify", action="store_true",
                       help="do not read the frames (fast; a frame with damaged data is not found)")
    add_quiet_argument(p)
    p.set_defaults(func=_replay_info)

    p = sub.add_parser("export", help="export a recording's frames as 8/16-bit PNG files")
    p.add_argument("path", type=Path)
    p.add_argument("--png", required=True, type=Path, metavar="DIR", help="output folder (created)")
    p.add_argument("--start", type=int, default=0, help="first frame index (default 0)")
    p.add_argument("--end", type=int, help="stop before this frame index (default: all)")
    p.add_argument("--every", type=int, default=1, help="export every N-th frame (default 1)")
    add_quiet_argument(p)
    p.set_defaults(func=_export)


def add_source_arguments(p: argparse.ArgumentParser) -> None:
    """The --source option and the common source options (shared with other verbs)."""
    p.add_argument("--source", required=True, metavar="SPEC",
                   help="gige[:DEVICE_ID], v4l2:/dev/videoN, images:GLOB_OR_DIR, replay:PATH or demo")
    add_camera_option(p, "pattern", "exposure pattern text or preset stored with the frames (e.g. 1,4/16,64), "
                                    "or a colour layout such as dual-iso")
    add_camera_option(p, "cfa", SOURCE_CFA_HELP)
    add_camera_option(p, "bits", "sensor bit depth (default: the pixel format's)")
    add_camera_option(p, "black_level", "sensor black level, DN")
    add_camera_option(p, "white_level", "sensor white level, DN")
    p.add_argument("--pixel-format", help="camera pixel format (e.g. Mono12Packed, Y16)")
    p.add_argument("--width", type=int, help="frame width / ROI width, pixels")
    p.add_argument("--height", type=int, help="frame height / ROI height, pixels")
    p.add_argument("--fps", type=float, help="frame rate (cameras, images, demo)")
    p.add_argument("--speed", type=float, help="replay speed factor (0: as fast as possible)")
    p.add_argument("--loop", action="store_true", default=None, help="loop images or replay")
    p.add_argument("--opt", action="append", default=[], metavar="KEY=VALUE",
                   help="any other source option, e.g. exposure_us=5000 (repeatable)")


def parse_opts(items: list[str]) -> dict[str, Any]:
    """``KEY=VALUE`` strings into a dict, values as int, float, bool or text."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise SveliveError(f"--opt {item!r}: expected KEY=VALUE")
        value: Any = text
        if text.lower() in ("true", "false"):
            value = text.lower() == "true"
        else:
            for cast in (int, float):
                try:
                    value = cast(text)
                    break
                except ValueError:
                    pass
        out[key.strip().replace("-", "_")] = value
    return out


def source_from_args(args: argparse.Namespace) -> Any:
    """Build the Source the common arguments describe."""
    opts = {**CameraSettings.from_args(args).source_options(), "pixel_format": args.pixel_format,
            "width": args.width, "height": args.height, "fps": args.fps, "speed": args.speed, "loop": args.loop}
    opts.update(parse_opts(args.opt))
    return open_source(args.source, **opts)


def _record(args: argparse.Namespace) -> int:
    if args.frames is not None and args.frames <= 0:
        raise SveliveError("--frames must be > 0")
    if args.seconds is not None and args.seconds <= 0:
        raise SveliveError("--seconds must be > 0")
    times = args.exposure_times or []
    if times and args.frames is None:
        raise SveliveError("--exposure-times needs --frames (the frames recorded at each time)")
    source = source_from_args(args)
    # the frames carry the camera (the user's pattern and colour filter included), which the writer stores
    if times:  # refused before the file exists: a camera without the control, a time a replay lacks
        try:
            stepped = exposure_steps(source.open(), times)
        except BaseException:
            source.close()
            raise
    writer = RecordingWriter(args.output, source=args.source,
                             config=WriterConfig(overwrite=args.overwrite, sync_every=args.sync_every))
    frames: queue.Queue[tuple[Frame, float | None] | None] = queue.Queue(maxsize=max(1, args.queue))
    failure: list[BaseException] = []
    dropped = 0

    def write_loop() -> None:
        while (item := frames.get()) is not None:
            if failure:
                continue
            try:
                writer.append(*item)
            except BaseException as exc:  # noqa: BLE001 - reported by the main thread
                failure.append(exc)

    previous = signal.signal(signal.SIGTERM, _raise_interrupt)
    thread = threading.Thread(target=write_loop, name="recorder", daemon=True)
    t0 = time.monotonic()
    interrupted = False
    progress = Progress("recording", total=None if args.frames is None else args.frames * max(1, len(times)),
                        quiet=args.quiet)
    try:
        with source, progress:
            thread.start()
            try:
                tagged = (stepped.frames(args.frames) if times else
                          ((f, None) for f in source.frames(limit=args.frames, seconds=args.seconds)))
                for item in tagged:
                    if failure:
                        break
                    try:
                        frames.put_nowait(item)
                    except queue.Full:
                        dropped += 1
                    progress.update()
            except KeyboardInterrupt:
                interrupted = True
            finally:
                if times:
                    stepped.restore()
            stats = source.stats()
    finally:
        if thread.is_alive():
            frames.put(None)
            thread.join()
        writer.close()
        signal.signal(signal.SIGTERM, previous)
    if failure:
        raise failure[0] if isinstance(failure[0], SveliveError) else SveliveError(str(failure[0]))
    summary = {"output": str(args.output), "frames": writer.frames, "seconds": round(time.monotonic() - t0, 3),
               "dropped_by_recorder": dropped, "source_drops": stats["drops"], "interrupted": interrupted}
    if times:
        summary.update(exposure_times=stepped.applied, exposure_time_restored=stepped.restored)

    print_json(summary)
    if writer.frames == 0:
        raise SveliveError(f"{args.source}: no frame was recorded, so no file was written")
    return 0


class ExposureSteps:
    """Frames of a source at each of several global exposure times in turn, then the time it had put back.

    After each change the frames that do not show it yet are skipped (:class:`AfterChange`, ``settle``
    frames). Each kept frame is tagged with the time the camera reported it applied.
    """

    def __init__(self, source: Any, times: list[float], settle: int = 1, timeout_s: float = 5.0) -> None:
        self.source, self.times, self.settle, self.timeout_s = source, times, settle, timeout_s
        self.original: float = source.exposure_time()
        self.applied: list[float] = []
        self.restored: float | None = None

    def frames(self, per_time: int) -> Iterator[tuple[Frame, float]]:
        """``per_time`` (frame, exposure time) pairs at each time, in order."""
        for t in self.times:
            applied = self.source.set_exposure_time(t)
            self.applied.append(applied)
            settled = AfterChange(time.monotonic_ns(), self.settle)
            kept = 0
            while kept < per_time:
                frame = self.source.read(timeout=self.timeout_s)
                if settled.shows(frame):
                    kept += 1
                    yield frame, applied

    def restore(self) -> None:
        """Put back the exposure time the source had before the first step."""
        self.restored = self.source.set_exposure_time(self.original)


def exposure_steps(source: Any, times: list[float]) -> ExposureSteps:
    """An :class:`ExposureSteps` over an open ``source``; a one-line SveliveError when it cannot set
    its exposure time or cannot take one of ``times`` (nothing is changed then)."""
    if source.exposure_time() is None:
        raise SveliveError(f"source {source.spec} cannot set its exposure time, so --exposure-times cannot "
                           "step it (GigE cameras with ExposureTime, the demo, and replays of recorded times can)")
    source.check_exposure_times(times)
    return ExposureSteps(source, times)


def _raise_interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt


def _replay_info(args: argparse.Namespace) -> int:

    with RecordingReader(args.path) as reader:
        info = reader.info()
        if not args.no_verify:
            damaged = _verify(reader, args.quiet)
            _add_verified(info, reader, damaged)
        print_json(info)
    return 1 if args.verify and info["verified"]["damaged"] else 0


def _add_verified(info: dict[str, Any], reader: RecordingReader, damaged: list[int]) -> None:
    """``info`` with what reading every frame found: ``verified`` (frames, intact, damaged), every damaged
    frame in ``damaged_records`` (the index rebuild finds only damaged record headers) and one warning
    line naming the frames with damaged data (also printed, as the reader's warnings are)."""
    info["verified"] = {"frames": len(reader), "intact": len(reader) - len(damaged), "damaged": damaged}
    info["damaged_records"] = sorted(set(info["damaged_records"]) | set(damaged))
    data = [i for i in damaged if i not in set(reader.damaged)]
    if data:
        line = (f"{reader.path}: {len(data)} of {len(reader)} frames damaged (data checksum mismatch: "
                f"{_ranges(data)}); export and reconstruct skip them")
        info["warnings"] = [*info["warnings"], line]
        report(line)


def _verify(reader: RecordingReader, quiet: bool) -> list[int]:
    """Indices of the frames whose record header or payload checksum fails, reading every frame."""
    damaged = []
    with Progress("verifying", total=len(reader), quiet=quiet) as progress:
        for i in range(len(reader)):
            try:
                reader.read(i)
            except CorruptFrameError:
                damaged.append(i)
            progress.update()
    return damaged


def _export(args: argparse.Namespace) -> int:
    from svelive.cli.reconstruct import write_raw

    if args.every < 1:
        raise SveliveError("--every must be >= 1")
    out: Path = args.png
    if out.exists() and not out.is_dir():
        raise SveliveError(f"{out}: exists and is not a folder")
    with RecordingReader(args.path) as reader:
        end = len(reader) if args.end is None else min(args.end, len(reader))
        if not 0 <= args.start < max(end, 1):
            raise SveliveError(f"--start {args.start} is outside the recording's {len(reader)} frames")
        out.mkdir(parents=True, exist_ok=True)
        indices = range(args.start, end, args.every)
        damaged: list[int] = []
        with Progress("exporting", total=len(indices), quiet=args.quiet) as progress:
            for i in indices:
                try:
                    raw = reader.read(i).raw
                except CorruptFrameError as exc:  # skipped and counted, as the replay source does
                    print(f"svelive export: warning: {exc}; skipped", file=sys.stderr)
                    damaged.append(i)
                else:
                    write_raw(out / f"frame_{i:06d}.png", raw, bits=reader.sensor.bits)  # sBIT: the depth
                progress.update()
    n = len(indices) - len(damaged)
    skipped = f" ({len(damaged)} damaged frames skipped: {', '.join(map(str, damaged))})" if damaged else ""
    if n == 0:
        raise SveliveError(f"{args.path}: no intact frame to export{skipped}")
    print(f"exported {n} frames to {out}{skipped}", file=sys.stderr)
    return 0
