"""Read a recording: metadata, the frame index, and any frame by number in constant time.

Opening a recording checks its header, then takes the index from the footer of
a cleanly closed file. Without one (the recorder was killed) or with a corrupt
one, it rebuilds the index by scanning the fixed-stride record headers: a
damaged record header in the middle is skipped (the records after it are at
their fixed offsets, so every intact frame is recovered; the damaged one keeps
its place and is listed in :attr:`RecordingReader.damaged`), and a torn last
record (short, or its payload checksum fails) is dropped. Every problem found
is kept in :attr:`RecordingReader.warnings` and reported with ``warnings.warn`` as a
:class:`RecordingWarning`, which prints as one plain line (``svelive: warning: ...``, no source
code) in the CLI and the service's log; frames that are readable stay readable.
"""

from __future__ import annotations

import bisect
import os
import sys
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from replay.container import (
    FILE_HEADER,
    FOOTER,
    FOOTER_MAGIC,
    HEADER_ALIGN,
    INDEX_HEADER,
    INDEX_MAGIC,
    NO_EXPOSURE,
    NO_TIME,
    RECORD_HEADER,
    RECORD_MAGIC,
    RecordingError,
    crc32,
    decode_header,
)
from svelive.core import formats
from svelive.core.camera import Camera
from svelive.core.cfa import ColourFilter
from svelive.core.errors import SveliveError
from svelive.core.frame import Frame


class CorruptFrameError(RecordingError):
    """One frame's checksum does not match: it was damaged after writing."""


class RecordingWarning(UserWarning):
    """A problem of a recording that leaves its readable frames readable (shown as one plain line)."""


def report(text: str) -> None:
    """Report ``text`` as a :class:`RecordingWarning` (one plain line on stderr in the ``svelive`` command,
    :func:`show_warnings_plainly`)."""
    warnings.warn(RecordingWarning(text), stacklevel=2)


_default_show = warnings.showwarning


def _show(message: Warning | str, category: type[Warning], filename: str, lineno: int,
          file: Any = None, line: str | None = None) -> None:
    """``warnings.showwarning`` that prints a RecordingWarning as ``svelive: warning: TEXT`` (Python's
    default shows the file, line and source code of the call); any other warning as before."""
    if not issubclass(category, RecordingWarning):
        _default_show(message, category, filename, lineno, file, line)
        return
    stream = sys.stderr if file is None else file
    try:
        stream.write(f"svelive: warning: {message}\n")
    except (OSError, AttributeError, ValueError):  # no stderr (a daemon): as Python's default, say nothing
        pass


def show_warnings_plainly() -> None:
    """Print RecordingWarnings as one plain line from now on (``svelive: warning: TEXT``). The ``svelive``
    command calls it; a library import changes no global state, so a program that uses svelive keeps its own
    warning display. Installed over Python's own hook only: one a host installed is left alone."""
    if getattr(warnings.showwarning, "__module__", None) == "warnings":
        warnings.showwarning = _show


class RecordingReader:
    """An open recording.

    Attributes:
        path: the file.
        meta: the header's JSON metadata (width, height, dtype, pixel_format, pattern, sensor, ...).
        layout: geometry (width, height, dtype, data offset, record size).
        times: int64 (N, 3): frame_id, host_time_ns, device_time_ns (``NO_TIME`` when absent).
        clean: True when the file was closed cleanly and its index was used.
        damaged: indices of records whose header was found damaged by the index rebuild (their
            ``times`` row repeats the nearest intact frame's times; reading them raises
            CorruptFrameError). Damaged payloads are only found by reading (:meth:`verify`).
        warnings: human-readable problems found while opening.

    ``warn=False`` keeps the problems in ``warnings`` without ``warnings.warn`` (a second
    opening of a file whose problems were already reported).
    """

    def __init__(self, path: str | os.PathLike, *, warn: bool = True) -> None:
        self.path = Path(path)
        self.warnings: list[str] = []
        self.damaged: tuple[int, ...] = ()
        if self.path.is_dir():
            raise RecordingError(f"{self.path}: is a directory, not a recording")
        if self.path.exists() and not self.path.is_file():  # a FIFO's open() waits for a writer: forever
            raise RecordingError(f"{self.path}: is not a regular file (a FIFO, socket or device), not a recording")
        try:
            self._f = open(self.path, "rb", buffering=0)  # noqa: SIM115 - closed in close()
        except FileNotFoundError:
            raise RecordingError(f"{self.path}: no such recording") from None
        except OSError as exc:
            raise RecordingError(f"{self.path}: cannot open ({exc.strerror})") from None
        try:
            self._open(warn)
        except BaseException:
            self._f.close()
            raise

    def _open(self, warn: bool) -> None:
        size = os.fstat(self._f.fileno()).st_size
        first = os.pread(self._f.fileno(), HEADER_ALIGN, 0)
        if len(first) >= FILE_HEADER.size:
            need = FILE_HEADER.size + FILE_HEADER.unpack_from(first)[2]
            if need > len(first) and first[:8] == FILE_HEADER.unpack_from(first)[0] and need < 1 << 24:
                first = os.pread(self._f.fileno(), need, 0)
        self.meta, self.layout = decode_header(first, str(self.path))
        try:
            self.pixel_format = formats.lookup(self.meta.get("pixel_format", "")).name
        except SveliveError:
            raise RecordingError(f"{self.path}: unknown pixel format {self.meta.get('pixel_format')!r} "
                                 "in the header") from None
        format_cfa = formats.lookup(self.pixel_format).cfa
        # recordings before the camera description stored pattern and sensor alone; a Bayer
        # pixel format then still says which colour filter the frames have
        described = self.meta.get("camera")
        if described is None:
            described = {"pattern": self.meta.get("pattern"), "sensor": self.meta.get("sensor") or {},
                         "cfa": format_cfa}
        try:
            self.camera = Camera.from_dict(described, default_bits=16 if self.layout.dtype == "uint16" else 8)
        except SveliveError as exc:
            raise RecordingError(f"{self.path}: camera metadata is invalid ({exc})") from None
        cfa = self.camera.cfa
        if format_cfa is not None and (cfa is None or (cfa.is_bayer() and cfa != ColourFilter.parse(format_cfa))):
            raise RecordingError(f"{self.path}: the header's camera has colour filter "
                                 f"{'none' if cfa is None else cfa.name} but the frames are {self.pixel_format} "
                                 f"({format_cfa}); the header was altered: correct its camera.cfa")
        self.sensor = self.camera.sensor
        self.pattern: str | None = None if self.camera.pattern is None else str(self.camera.pattern)
        self._size = size
        times = self._read_index(size)
        self.clean = times is not None
        if times is None:
            times = self._scan(size)
        self.times = times
        self.times.setflags(write=False)
        self._exposures: np.ndarray | None = None
        if warn:
            for w in self.warnings:
                report(w)

    def _warn(self, text: str) -> None:
        self.warnings.append(f"{self.path}: {text}")

    def _read_index(self, size: int) -> np.ndarray | None:
        lay = self.layout
        fd = self._f.fileno()
        if size < lay.data_offset + FOOTER.size:
            return None
        magic, offset, crc, _ = FOOTER.unpack(os.pread(fd, FOOTER.size, size - FOOTER.size))
        if magic != FOOTER_MAGIC:
            self._warn("no index (the recording was not closed cleanly); rebuilt it by scanning")
            return None
        if crc32(FOOTER_MAGIC + offset.to_bytes(8, "little")) != crc or offset < lay.data_offset \
                or offset > size - FOOTER.size - INDEX_HEADER.size:
            self._warn("corrupt index footer; rebuilt the index by scanning")
            return None
        imagic, count, icrc, _ = INDEX_HEADER.unpack(os.pread(fd, INDEX_HEADER.size, offset))
        table_bytes = count * 24
        ok = imagic == INDEX_MAGIC and offset + INDEX_HEADER.size + table_bytes + FOOTER.size == size \
            and offset == lay.data_offset + count * lay.record_size
        if ok:
            raw = os.pread(fd, table_bytes, offset + INDEX_HEADER.size)
            ok = len(raw) == table_bytes and crc32(raw) == icrc
        if not ok:
            self._warn("corrupt index; rebuilt it by scanning")
            return None
        return np.frombuffer(raw, dtype="<i8").reshape(count, 3).astype(np.int64)

    def _scan(self, size: int) -> np.ndarray:
        lay = self.layout
        fd = self._f.fileno()
        n_max = max(0, (size - lay.data_offset) // lay.record_size)
        rows: list[tuple[int, int, int] | None] = []
        ended = False  # an index (of a close that did not finish its footer) follows the records
        for i in range(n_max):
            head = os.pread(fd, RECORD_HEADER.size, lay.data_offset + i * lay.record_size)
            if head[:4] == INDEX_MAGIC:
                ended = True
                break
            rows.append(self._parse_record_header(head, i))
        while rows and rows[-1] is None:  # damaged records after the last intact one: a torn end
            rows.pop()
        if not ended:
            tail = size - lay.data_offset - n_max * lay.record_size
            if tail > 0 and os.pread(fd, 4, lay.data_offset + n_max * lay.record_size) != INDEX_MAGIC:
                self._warn(f"torn last frame ({tail} of {lay.record_size} bytes) skipped")
        if rows:  # the last complete record may still be torn inside its payload
            try:
                self._payload(len(rows) - 1)
            except CorruptFrameError:
                rows.pop()
                self._warn(f"torn last frame {len(rows)} (checksum mismatch) skipped")
                while rows and rows[-1] is None:
                    rows.pop()
        self.damaged = tuple(i for i, row in enumerate(rows) if row is None)
        if self.damaged:
            self._warn(f"{len(self.damaged)} damaged record(s) skipped ({_ranges(self.damaged)}); "
                       f"kept the {len(rows) - len(self.damaged)} intact frames")
        return _fill_damaged(rows)

    def _parse_record_header(self, head: bytes, index: int) -> tuple[int, int, int] | None:
        if len(head) != RECORD_HEADER.size:
            return None
        magic, hcrc, idx, fid, host, dev, plen, _, _ = RECORD_HEADER.unpack(head)
        if magic != RECORD_MAGIC or crc32(head[8:]) != hcrc or idx != index or plen != self.layout.payload_size:
            return None
        return fid, host, dev

    # ----- public --------------------------------------------------------
    def __len__(self) -> int:
        return int(self.times.shape[0])

    @property
    def frames(self) -> int:
        """Number of replayable frames."""
        return len(self)

    @property
    def duration_s(self) -> float:
        """Time from the first to the last frame (device clock when every frame has one), seconds."""
        t = self.timeline_ns()
        return float(t[-1] - t[0]) / 1e9 if len(t) > 1 else 0.0

    @property
    def clock(self) -> str:
        """"device" when every frame has a device timestamp, else "host"."""
        dev = self.times[:, 2]
        return "device" if len(dev) and bool(np.all(dev != NO_TIME)) else "host"

    def timeline_ns(self) -> np.ndarray:
        """int64 (N,) presentation times in ns: device timestamps if all frames have them, else host."""
        return self.times[:, 2] if self.clock == "device" else self.times[:, 1]

    def _payload(self, i: int) -> tuple[np.ndarray, tuple[int, int, int], float]:
        lay = self.layout
        buf = bytearray(RECORD_HEADER.size + lay.payload_size)
        n = os.preadv(self._f.fileno(), [buf], lay.data_offset + i * lay.record_size)
        if n != len(buf):
            raise CorruptFrameError(f"{self.path}: frame {i} is truncated")
        head = bytes(buf[: RECORD_HEADER.size])
        parsed = self._parse_record_header(head, i)
        if parsed is None:
            raise CorruptFrameError(f"{self.path}: frame {i} has a damaged record header")
        body = memoryview(buf)[RECORD_HEADER.size:]
        fields = RECORD_HEADER.unpack(head)
        if crc32(body) != fields[7]:
            raise CorruptFrameError(f"{self.path}: frame {i} checksum mismatch (damaged data)")
        arr = np.frombuffer(buf, dtype=np.dtype(lay.dtype).newbyteorder("<"), offset=RECORD_HEADER.size,
                            count=lay.width * lay.height).reshape(lay.height, lay.width)
        return arr, parsed, fields[8]

    def read(self, i: int) -> Frame:
        """Frame ``i`` (0-based; negative counts from the end), checksum verified.

        Returns a Frame whose ``raw`` is uint8/uint16 (H, W), with the recorded
        frame id and timestamps. Raises CorruptFrameError when the data was damaged.
        """
        n = len(self)
        if not -n <= i < n:
            raise RecordingError(f"{self.path}: frame {i} out of range (the recording has {n} frames)")
        i %= n
        arr, (fid, host, dev), exposure = self._payload(i)
        if arr.dtype.byteorder not in ("=", "|"):
            arr = arr.astype(arr.dtype.newbyteorder("="))
        return Frame(raw=arr, frame_id=int(fid), host_time_ns=int(host),
                     device_time_ns=None if dev == NO_TIME else int(dev),
                     pixel_format=self.pixel_format, camera=self.camera,
                     exposure_time=None if exposure == NO_EXPOSURE or not np.isfinite(exposure) else float(exposure))

    def exposure_times(self) -> np.ndarray:
        """float64 (N,): each frame's recorded global exposure time (the camera's unit, GigE
        microseconds), NaN where none was recorded (recordings made before the field existed,
        sources that cannot tell) or the record header is damaged.

        Read from the record headers on the first call (one 64-byte read per frame), then kept.
        """
        if self._exposures is None:
            lay = self.layout
            fd = self._f.fileno()
            out = np.full(len(self), np.nan)
            for i in range(len(self)):
                head = os.pread(fd, RECORD_HEADER.size, lay.data_offset + i * lay.record_size)
                if self._parse_record_header(head, i) is not None:
                    value = RECORD_HEADER.unpack(head)[8]
                    if value != NO_EXPOSURE and np.isfinite(value):
                        out[i] = value
            out.setflags(write=False)
            self._exposures = out
        return self._exposures

    def verify(self) -> list[int]:
        """Read every frame and check its checksums; returns the indices of the damaged ones (sorted)."""
        bad = []
        for i in range(len(self)):
            try:
                self._payload(i)
            except CorruptFrameError:
                bad.append(i)
        return bad

    def info(self) -> dict[str, Any]:
        """A JSON-ready summary (what ``svelive replay-info`` prints)."""
        lay = self.layout
        t = self.timeline_ns()
        return {
            "path": str(self.path), "frames": len(self), "width": lay.width, "height": lay.height,
            "dtype": lay.dtype, "pixel_format": self.pixel_format, "pattern": self.pattern,
            "cfa": None if self.camera.cfa is None else self.camera.cfa.name,
            "sensor": {"bits": self.sensor.bits, "black_level": self.sensor.black_level,
                       "white_level": self.sensor.white_level, "gain": self.sensor.gain,
                       "read_noise": self.sensor.read_noise},
            "duration_s": round(self.duration_s, 6),
            "fps": round((len(t) - 1) / self.duration_s, 3) if self.duration_s > 0 else None,
            "clock": self.clock,
            "closed_cleanly": self.clean, "source": self.meta.get("source"), "created": self.meta.get("created"),
            "bytes": self._size, "damaged_records": list(self.damaged), "warnings": list(self.warnings),
            "exposure_times": _exposure_counts(self.exposure_times()),
        }

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> RecordingReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _fill_damaged(rows: list[tuple[int, int, int] | None]) -> np.ndarray:
    """int64 (N, 3) times of the scanned records: a damaged record (None) takes the nearest earlier
    intact record's times (the next one's at the start), frame_id advanced by its distance, so
    the timeline stays ordered."""
    out = np.zeros((len(rows), 3), np.int64)
    known = [i for i, row in enumerate(rows) if row is not None]
    for i, row in enumerate(rows):
        if row is not None:
            out[i] = row
            continue
        j = bisect.bisect_left(known, i)
        k = known[j - 1] if j else known[0]
        out[i] = rows[k]
        out[i, 0] += i - k
    return out


def _exposure_counts(exposures: np.ndarray) -> list[list[float | int]] | None:
    """[[exposure time, frames], ...] by increasing time for the frames that have one; None when none has."""
    known = exposures[np.isfinite(exposures)]
    if known.size == 0:
        return None
    values, counts = np.unique(known, return_counts=True)
    return [[float(v), int(n)] for v, n in zip(values, counts)]


def _ranges(indices: tuple[int, ...] | list[int]) -> str:
    """``"3, 7-9"`` for (3, 7, 8, 9)."""
    parts: list[str] = []
    start = prev = indices[0]
    for i in (*indices[1:], None):
        if i is not None and i == prev + 1:
            prev = i
            continue
        parts.append(str(start) if start == prev else f"{start}-{prev}")
        if i is not None:
            start = prev = i
    return ", ".join(parts)
