"""Append frames to a recording, crash-safely.

Frames are appended with one ``os.writev`` each (record header, the frame's own
memory, padding: no copy of the pixels). Nothing is rewritten in place: after a
crash or ``kill -9`` every record written before stays valid, and only the last
one may be torn, which the reader detects by its checksum. ``close()`` appends
the index and footer; ``sync_every`` makes the writer ``fdatasync`` so that a
power loss (not only a process kill) loses at most that many frames.
"""

from __future__ import annotations

import datetime
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from replay.container import (
    FOOTER,
    FOOTER_MAGIC,
    INDEX_HEADER,
    INDEX_MAGIC,
    NO_EXPOSURE,
    NO_TIME,
    RECORD_ALIGN,
    RECORD_HEADER,
    RECORD_MAGIC,
    Layout,
    RecordingError,
    crc32,
    encode_header,
)
from svelive.core import formats
from svelive.core.atomic import check_output_target
from svelive.core.cfa import ColourFilter
from svelive.core.errors import SveliveError
from svelive.core.frame import Frame
from svelive.core.sensor import Sensor


@dataclass(frozen=True)
class WriterConfig:
    """How a recording is written.

    Attributes:
        overwrite: replace an existing file (it is removed when the first frame arrives).
        sync_every: fdatasync after this many frames (0: never; the page cache
            still survives a process kill).
    """

    overwrite: bool = False
    sync_every: int = 0


def sensor_dict(sensor: Sensor) -> dict[str, Any]:
    """JSON form of a Sensor."""
    return {"bits": sensor.bits, "black_level": sensor.black_level, "white_level": sensor.white_level,
            "gain": sensor.gain, "read_noise": sensor.read_noise}


class RecordingWriter:
    """Writes one recording. Use as a context manager; frames via :meth:`append`.

    The file is created when the first frame arrives (its size, dtype and pixel
    format fix the layout); every later frame must match them.
    """

    def __init__(self, path: str | os.PathLike, *, pattern: str | None = None, source: str | None = None,
                 config: WriterConfig | None = None, extra: dict[str, Any] | None = None) -> None:
        self.path = Path(path)
        self.config = config or WriterConfig()
        self.pattern = pattern
        self.source = source
        self.extra = dict(extra or {})
        self._fd: int | None = None
        self._layout: Layout | None = None
        self._pixel_format: str | None = None
        self._times: list[tuple[int, int, int]] = []
        self._closed = False
        if self.path.is_dir():
            raise RecordingError(f"{self.path}: is a directory; give a file name for the recording")
        if not self.path.parent.is_dir():
            raise RecordingError(f"{self.path}: folder {self.path.parent} does not exist")
        if self.path.exists() and not self.config.overwrite:
            raise RecordingError(f"{self.path}: already exists (use --overwrite to replace it)")
        check_output_target(self.path)  # --overwrite replaces a regular file, never a device, FIFO or link

    @property
    def frames(self) -> int:
        """Frames appended so far."""
        return len(self._times)

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _camera_dict(self, frame: Frame) -> dict[str, Any]:
        """The frame's camera description, with the writer's pattern where one was given.

        A Bayer pixel format and the camera's colour filter must agree, as the reader
        checks; a camera without one (a hand-made Frame) takes the format's.
        """
        camera = frame.camera if self.pattern is None else frame.camera.with_pattern(self.pattern)
        named = formats.lookup(frame.pixel_format).cfa
        if named is not None:
            if camera.cfa is None:
                camera = camera.replace(cfa=ColourFilter.parse(named))
            elif camera.cfa.is_bayer() and camera.cfa != ColourFilter.parse(named):
                raise RecordingError(f"frame {frame.frame_id} is {frame.pixel_format} (colour filter {named}) but "
                                     f"its camera says {camera.cfa.name}; give the source the right --cfa")
        return camera.to_dict()

    def _start(self, frame: Frame) -> None:
        raw = frame.raw
        if raw.ndim != 2 or raw.dtype not in (np.uint8, np.uint16):
            raise RecordingError(f"frames must be uint8 or uint16 (H, W), got {raw.dtype} {raw.shape}")
        try:
            formats.lookup(frame.pixel_format)
        except SveliveError as exc:
            raise RecordingError(f"{self.path}: {exc}") from None
        h, w = raw.shape
        meta = {
            "format": "svelive-recording", "width": w, "height": h, "dtype": raw.dtype.name,
            "pixel_format": frame.pixel_format, "pattern": self.pattern or frame.camera.to_dict()["pattern"],
            "sensor": sensor_dict(frame.sensor), "camera": self._camera_dict(frame),
            "source": self.source, "created": datetime.datetime.now(datetime.timezone.utc).isoformat(),
            **self.extra,
        }
        head = encode_header(meta)
        self._layout = Layout(w, h, raw.dtype.name, len(head))
        self._pixel_format = frame.pixel_format
        self._sensor = frame.sensor
        flags = os.O_WRONLY | os.O_CREAT | os.O_APPEND | getattr(os, "O_CLOEXEC", 0)
        if self.config.overwrite:
            check_output_target(self.path)
            try:
                os.unlink(self.path)
            except FileNotFoundError:
                pass
        try:
            self._fd = os.open(self.path, flags | os.O_EXCL, 0o644)
        except FileExistsError:
            raise RecordingError(f"{self.path}: already exists (use --overwrite to replace it)") from None
        except OSError as exc:
            raise RecordingError(f"{self.path}: cannot create ({exc.strerror})") from None
        self._write([head])

    def _write(self, parts: list) -> None:
        assert self._fd is not None
        total = sum(memoryview(p).nbytes for p in parts)
        try:
            n = os.writev(self._fd, parts)
            if n != total:  # a short write (disk full): finish it or fail
                rest = b"".join(bytes(memoryview(p).cast("B")) for p in parts)[n:]
                while rest:
                    k = os.write(self._fd, rest)
                    rest = rest[k:]
        except OSError as exc:
            raise RecordingError(f"{self.path}: write failed ({exc.strerror})") from None

    def append(self, frame: Frame, exposure_time: float | None = None) -> None:
        """Append one frame (uint8/uint16 (H, W) of the recording's size, dtype and pixel format).

        ``exposure_time``: the camera's global exposure time for this frame, in its own unit
        (GigE: microseconds), a positive number; None takes the frame's ``exposure_time``
        attribute when it has one, else records none. A replay can then be swept
        (``ReplaySource.set_exposure_time`` plays the frames recorded at one time).
        """
        if exposure_time is None:
            exposure_time = getattr(frame, "exposure_time", None)
        if exposure_time is not None and not (math.isfinite(exposure_time) and exposure_time > 0):
            raise RecordingError(f"frame {frame.frame_id}: exposure time must be a positive number, "
                                 f"got {exposure_time}")
        if self._closed:
            raise RecordingError(f"{self.path}: recording is closed")
        if self._fd is None:
            self._start(frame)
        lay = self._layout
        assert lay is not None
        raw = frame.raw
        if raw.shape != (lay.height, lay.width) or raw.dtype.name != lay.dtype:
            raise RecordingError(
                f"frame {frame.frame_id} is {raw.shape[-1]}x{raw.shape[0]} {raw.dtype} but the recording is "
                f"{lay.width}x{lay.height} {lay.dtype}; start a new recording for a new frame size")
        if frame.pixel_format != self._pixel_format:
            raise RecordingError(f"frame {frame.frame_id} is {frame.pixel_format} but the recording is "
                                 f"{self._pixel_format}; start a new recording for a new pixel format")
        data = np.ascontiguousarray(raw)
        if data.dtype.byteorder == ">":
            data = data.astype(data.dtype.newbyteorder("<"))
        payload_crc = crc32(data)
        dev = NO_TIME if frame.device_time_ns is None else int(frame.device_time_ns)
        index = len(self._times)
        body = RECORD_HEADER.pack(RECORD_MAGIC, 0, index, int(frame.frame_id), int(frame.host_time_ns), dev,
                                  lay.payload_size, payload_crc,
                                  NO_EXPOSURE if exposure_time is None else float(exposure_time))
        head = body[:4] + (crc32(body[8:])).to_bytes(4, "little") + body[8:]
        pad = b"\0" * (lay.record_size - RECORD_HEADER.size - lay.payload_size)
        self._write([head, memoryview(data).cast("B"), pad] if pad else [head, memoryview(data).cast("B")])
        self._times.append((int(frame.frame_id), int(frame.host_time_ns), dev))
        if self.config.sync_every and len(self._times) % self.config.sync_every == 0:
            os.fdatasync(self._fd)

    def close(self) -> None:
        """Append the index and footer, sync and close. A recording with no frame leaves no file."""
        if self._closed:
            return
        self._closed = True
        if self._fd is None:
            return
        try:
            lay = self._layout
            assert lay is not None
            offset = lay.data_offset + len(self._times) * lay.record_size
            table = np.asarray(self._times, dtype="<i8").reshape(-1, 3)
            index = INDEX_HEADER.pack(INDEX_MAGIC, len(self._times), crc32(table), 0)
            tail = FOOTER_MAGIC + offset.to_bytes(8, "little")
            footer = FOOTER.pack(FOOTER_MAGIC, offset, crc32(tail), 0)
            self._write([index, memoryview(table).cast("B"), footer])
            os.fsync(self._fd)
        finally:
            os.close(self._fd)
            self._fd = None


assert RECORD_ALIGN % 8 == 0
