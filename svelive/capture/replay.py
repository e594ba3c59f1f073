"""``replay:PATH``: play an svelive recording back as a live source.

Timing: ``speed`` 1.0 replays at the recorded timing (device clock when every
frame has one, else the host clock), 2.0 twice as fast, 0 as fast as
possible. ``loop`` starts again after the last frame, ``start`` is the first
frame index (constant-time seek). Frames keep their recorded ``frame_id``
(shifted by the recording's id span on each loop so ids keep increasing) and
``device_time_ns``; ``host_time_ns`` is the delivery time. A frame whose
checksum fails is dropped (cause ``checksum``) with a warning.

``bits``, ``black_level`` and ``white_level`` replace the recorded sensor's (a
recording made with wrong levels); ``pattern`` the recorded pattern. A path
that is missing, a directory, or not a recording with frames fails when the
source is built, with a one-line error.
"""

from __future__ import annotations

import dataclasses
from dataclasses import replace
import time
import warnings
from dataclasses import dataclass
from typing import Any

from replay import CorruptFrameError, RecordingReader
from svelive.capture import make_config
from svelive.capture.source import EndOfStream, Source
from svelive.errors import SveliveError
from svelive.frame import Frame
from svelive.sensor import Sensor


@dataclass(frozen=True)
class ReplayConfig:
    """Options of the replay source.

    Attributes:
        speed: playback speed factor; 1.0 recorded timing, 0 as fast as possible.
        loop: start again after the last frame.
        start: index of the first frame played.
    """

    speed: float = 1.0
    loop: bool = False
    start: int = 0


class ReplaySource(Source):
    """Frames of a recording; see the module docstring."""

    def __init__(self, spec: str, arg: str | None, *, pattern: str | None = None, sensor: Sensor | None = None,
                 cfa: str | None = None, bits: int | None = None, black_level: float | None = None,
                 white_level: float | None = None, **opts: Any) -> None:
        super().__init__(spec, pattern=pattern, sensor=sensor, cfa=cfa)
        self.config: ReplayConfig = make_config(ReplayConfig, opts, spec)
        if self.config.speed < 0:
            raise SveliveError(f"{spec}: speed must be >= 0 (0 = as fast as possible), got {self.config.speed}")
        self._path = arg or ""
        self._reader: RecordingReader | None = None
        # the user's pattern as parsed (a colour layout's exposures), or None for the recorded one
        self._override = (None if pattern is None else self.camera.pattern, sensor)
        self._levels = {k: v for k, v in (("bits", bits), ("black_level", black_level),
                                          ("white_level", white_level)) if v is not None}
        # a recording that can never be replayed fails here, when the source is built (a service
        # builds its source once at start-up and would otherwise retry it for ever)
        with RecordingReader(self._path) as reader:
            self._check(reader)

    def _check(self, reader: RecordingReader) -> None:
        """Check that ``reader`` has frames to play from ``start`` and settle the camera from its header."""
        n = len(reader)
        if n == 0:
            raise SveliveError(f"{self._path}: the recording has no replayable frames")
        if not -n <= self.config.start < n:
            raise SveliveError(f"{self.spec}: start frame {self.config.start} out of range (0..{n - 1})")
        recorded = reader.camera
        pattern, sensor = self._override
        if sensor is None:
            try:
                sensor = replace(recorded.sensor, **self._levels)
            except (TypeError, ValueError, SveliveError) as exc:
                raise SveliveError(f"{self.spec}: sensor levels {self._levels} do not fit the recording ({exc})") \
                    from None
        self.camera = recorded if pattern is None else recorded.with_pattern(pattern)
        # the recorded colour filter stands for a pixel format: the user may not contradict it
        self._settle_camera(sensor, None if recorded.cfa is None else str(recorded.cfa),
                            f"{reader.pixel_format} frames")

    def _open(self) -> None:
        self._reader = RecordingReader(self._path, warn=False)  # its problems were reported when built
        try:
            self._check(self._reader)
        except SveliveError:
            self._reader.close()
            raise
        n = len(self._reader)
        self._timeline = self._reader.timeline_ns()
        ids = self._reader.times[:, 0]
        self._id_span = int(ids.max() - ids.min() + 1)
        self._pos = self.config.start % n
        self._loops = 0
        self._anchor: tuple[float, int] | None = None  # (wall time, recorded time) of the pacing origin

    def _close(self) -> None:
        if self._reader is not None:
            self._reader.close()

    def _next(self) -> Frame | None:
        reader = self._reader
        assert reader is not None
        if self._pos >= len(reader):
            if not self.config.loop:
                raise EndOfStream
            self._pos = 0
            self._loops += 1
            self._anchor = None
        i = self._pos
        if self.config.speed > 0:
            t_rec = int(self._timeline[i])
            if self._anchor is None:
                self._anchor = (time.monotonic(), t_rec)
            due = self._anchor[0] + (t_rec - self._anchor[1]) / 1e9 / self.config.speed
            if not self._wait(min(due - time.monotonic(), self.poll_s)):
                return None
            if time.monotonic() < due:
                return None
        self._pos += 1
        try:
            rec = reader.read(i)
        except CorruptFrameError as exc:
            warnings.warn(str(exc), stacklevel=2)
            self._drop("checksum")
            return None
        return dataclasses.replace(rec, frame_id=rec.frame_id + self._loops * self._id_span,
                                   host_time_ns=time.monotonic_ns(), camera=self.camera)

    def _extra_stats(self) -> dict[str, Any]:
        r = self._reader
        return {"position": getattr(self, "_pos", 0), "recording_frames": 0 if r is None else len(r),
                "loops": getattr(self, "_loops", 0), "speed": self.config.speed}
