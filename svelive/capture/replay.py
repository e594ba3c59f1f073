"""``replay:PATH``: play an svelive recording back as a live source.

Timing: ``speed`` 1.0 replays at the recorded timing (device clock when every
frame has one, else the host clock), 2.0 twice as fast, 0 as fast as
possible. ``loop`` starts again after the last frame, ``start`` is the first
frame index (constant-time seek). Frames keep their recorded ``frame_id``
(shifted by the recording's id span on each loop so ids keep increasing) and
``device_time_ns``; ``host_time_ns`` is the delivery time. A frame whose
checksum fails is dropped (cause ``checksum``) with a warning. A source rebuilt after a
failure (the service reopens it) goes on after the last frame the failed one delivered
(:meth:`ReplaySource.resume_after`).

``bits``, ``black_level`` and ``white_level`` replace the recorded sensor's (a
recording made with wrong levels); ``pattern`` the recorded pattern. A path
that is missing, a directory, or not a recording with frames fails when the
source is built, with a one-line error.

Exposure control: a recording whose frames carry their exposure time (the writer's
``exposure_time``, e.g. a GigE camera's ``ExposureTime``) behaves like a camera with
``ExposureTime``: :meth:`ReplaySource.set_exposure_time` picks the recorded time nearest
the one asked (within :data:`EXPOSURE_TOLERANCE`, as a camera rounds to its steps) and
from then on plays only the frames recorded at that time, in recorded order, over and
over (whatever ``loop`` says: a camera keeps delivering) at the recording's mean frame
rate; it returns the time picked, as a camera reads back the value it applied. The first
frame of every run of frames at one time is left out when other frames at that time
remain (it may have been exposed before the change, like the frame in flight of a live
camera). :meth:`~ReplaySource.exposure_time` is then that time; before any choice, the
time of the frame played last (or about to be played). A recording without exposure
times has no exposure control (``exposure_time()`` is None; setting it is refused).
After a sweep the service sets the time it had before, so the replay goes on with the
frames recorded at that time only.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from replay import CorruptFrameError, RecordingReader
from replay.reader import report
from svelive.capture import make_config
from svelive.capture.source import EndOfStream, Source
from svelive.core.errors import SveliveError
from svelive.core.frame import Frame
from svelive.core.sensor import Sensor

#: largest relative difference between an exposure time asked of a replay and the recorded one it picks
EXPOSURE_TOLERANCE = 0.02


def frames_at(exposures: np.ndarray, value: float) -> np.ndarray:
    """Indices (int64, increasing) of the frames recorded at exposure ``value``, less the first of
    each run of consecutive frames at it when that leaves any (it may have been exposed before the
    change). ``exposures``: float64 (N,), NaN where none was recorded."""
    at = exposures == value
    first = at & ~np.concatenate(([False], at[:-1]))
    kept = np.flatnonzero(at & ~first)
    return kept if kept.size else np.flatnonzero(at)


def pick_exposure(exposures: np.ndarray, value: float, where: str) -> float:
    """The recorded exposure time nearest ``value`` within EXPOSURE_TOLERANCE (relative); a one-line
    SveliveError listing the recorded times otherwise."""
    recorded = np.unique(exposures[np.isfinite(exposures)])
    if not (math.isfinite(value) and value > 0):
        raise SveliveError(f"{where}: exposure time must be a positive number, got {value}")
    nearest = float(recorded[np.argmin(np.abs(recorded - value))])
    if abs(nearest - value) > EXPOSURE_TOLERANCE * value:
        listed = ", ".join(f"{t:g}" for t in recorded[:16]) + (", ..." if recorded.size > 16 else "")
        raise SveliveError(f"{where}: no frame was recorded at exposure time {value:g} (recorded: {listed}); "
                           "sweep over recorded times")
    return nearest


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
        # exposure control: the recorded times (read at the first use), the time chosen and its frames
        self._select_lock = threading.Lock()
        self._exposures: np.ndarray | None = None
        self._chosen: float | None = None
        self._selection: np.ndarray | None = None
        self._sel_pos = 0
        self._switched = False  # a new time was chosen: the next frame starts its selection
        self._last_index: int | None = None
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
        # playing a chosen exposure time: one frame per mean recorded frame interval
        self._period_ns = int((self._timeline[-1] - self._timeline[0]) / (n - 1)) if n > 1 else 0
        self._sel_n = 0

    def resume_after(self, frame: Frame) -> None:
        """Continue after ``frame`` (delivered by an earlier source of this recording): the next frame is the
        one recorded after it, and the ids go on from its loop. A frame that is not from this recording
        changes nothing. The exposure time chosen on the earlier source is not carried over."""
        reader = self._reader
        if reader is None:
            raise SveliveError(f"{self.spec}: resume_after needs an open source")
        ids = reader.times[:, 0]
        first = int(ids.min())
        loops, offset = divmod(int(frame.frame_id) - first, self._id_span)
        at = np.flatnonzero(ids == first + offset)
        if loops < 0 or at.size == 0:
            return
        self._loops, self._pos, self._anchor = loops, int(at[0]) + 1, None

    def _close(self) -> None:
        if self._reader is not None:
            self._reader.close()

    # ----- exposure control ------------------------------------------------
    def _recorded_exposures(self) -> np.ndarray:
        """float64 (N,) recorded exposure times (NaN: none), read once."""
        if self._exposures is None:
            if self._reader is not None:
                self._exposures = self._reader.exposure_times()
            else:
                with RecordingReader(self._path, warn=False) as reader:
                    self._exposures = reader.exposure_times()
        return self._exposures

    def _settable_exposures(self) -> np.ndarray:
        """The recorded exposure times; a one-line SveliveError when the recording has none."""
        exposures = self._recorded_exposures()
        if not np.isfinite(exposures).any():
            raise SveliveError(f"source {self.spec} cannot set its exposure time: the recording has no "
                               "exposure times (record from a camera that reports them)")
        return exposures

    def exposure_time(self) -> float | None:
        """The exposure time chosen, else the recorded time of the frame played last (or next); None
        when the recording has no exposure times."""
        exposures = self._recorded_exposures()
        known = np.isfinite(exposures)
        if not known.any():
            return None
        with self._select_lock:
            if self._chosen is not None:
                return self._chosen
            i = self._last_index if self._last_index is not None else getattr(self, "_pos", self.config.start)
        i %= exposures.size
        return float(exposures[i]) if known[i] else float(exposures[np.flatnonzero(known)[0]])

    def set_exposure_time(self, value: float) -> float:
        """Play only the frames recorded at the time nearest ``value`` (see the module docstring);
        returns that time. A one-line SveliveError when the recording has no exposure times or
        none near ``value``."""
        exposures = self._settable_exposures()
        chosen = pick_exposure(exposures, float(value), self.spec)
        with self._select_lock:
            self._chosen, self._selection, self._sel_pos = chosen, frames_at(exposures, chosen), 0
            self._switched = True
        return chosen

    def check_exposure_times(self, values: list[float]) -> None:
        """A one-line SveliveError naming the first of ``values`` the recording holds no frame at."""
        exposures = self._settable_exposures()
        for value in values:
            pick_exposure(exposures, float(value), self.spec)

    def _selected(self) -> tuple[int, np.ndarray] | None:
        """The next frame index while an exposure time is chosen and the selection it is from (None
        while none is chosen); starts a new choice's pacing and frame ids."""
        with self._select_lock:
            selection = self._selection
            if selection is None:
                return None
            if self._switched:  # a new choice: frame ids jump past every one so far
                self._switched = False
                self._loops += 1
                self._anchor, self._sel_n = None, 0
            if self._sel_pos >= selection.size:
                self._sel_pos = 0
                self._loops += 1
            return int(selection[self._sel_pos]), selection

    def _next(self) -> Frame | None:
        reader = self._reader
        assert reader is not None
        chosen = self._selected()
        if chosen is not None:
            return self._next_selected(reader, *chosen)
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
        return self._deliver_index(reader, i)

    def _next_selected(self, reader: RecordingReader, i: int, selection: np.ndarray) -> Frame | None:
        """Frame ``i`` of the chosen exposure time's ``selection``, paced at the recording's mean
        frame rate; None when another time was chosen meanwhile (its frames come next)."""
        if self.config.speed > 0 and self._period_ns > 0:
            if self._anchor is None:
                self._anchor = (time.monotonic(), 0)
            due = self._anchor[0] + self._sel_n * self._period_ns / 1e9 / self.config.speed
            if not self._wait(min(due - time.monotonic(), self.poll_s)):
                return None
            if time.monotonic() < due:
                return None
        with self._select_lock:
            if self._selection is not selection:
                return None
            self._sel_pos += 1
        self._sel_n += 1
        return self._deliver_index(reader, i)

    def _deliver_index(self, reader: RecordingReader, i: int) -> Frame | None:
        try:
            rec = reader.read(i)
        except CorruptFrameError as exc:
            report(str(exc))  # one plain line, not Python's warning with its source line
            self._drop("checksum")
            return None
        self._last_index = i
        return dataclasses.replace(rec, frame_id=rec.frame_id + self._loops * self._id_span,
                                   host_time_ns=time.monotonic_ns(), camera=self.camera)

    def _extra_stats(self) -> dict[str, Any]:
        r = self._reader
        return {"position": getattr(self, "_pos", 0), "recording_frames": 0 if r is None else len(r),
                "loops": getattr(self, "_loops", 0), "speed": self.config.speed, "exposure_time": self._chosen}
