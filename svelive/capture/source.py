"""The one interface every frame source implements.

A :class:`Source` is opened (or used as a context manager), iterated for
:class:`svelive.core.frame.Frame` objects, and closed. ``close()`` may be called
from any thread: an iteration in progress then ends within
``Source.poll_s`` plus the time of one blocking camera call (bounded, 0.1 s
by default), so a capture thread can be stopped cleanly. ``stats()`` is safe to
call from any thread at any time.

Subclasses implement ``_open()``, ``_close()`` and ``_next()``: ``_next`` returns
a Frame, None when no frame is ready yet (it is called again unless the source
is closing), or raises :class:`EndOfStream` when a finite source is exhausted.
Subclasses count dropped frames with ``self._drop(cause)`` and report liveness
with ``self._set_online(bool)``.
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

from svelive.core.camera import Camera
from svelive.core.cfa import ColourFilter
from svelive.core.errors import SveliveError
from svelive.core.frame import Frame
from svelive.core.sensor import Sensor

#: ``cfa`` values that say "this sensor has no colour filter".
MONO_WORDS = ("none", "mono")


def resolve_cfa(given: str | ColourFilter | None, format_cfa: str | None, format_name: str | None,
                offset: tuple[int, int] = (0, 0), where: str = "source") -> ColourFilter | None:
    """The colour filter of a source's frames, from what the user gave and what the pixel format says.

    Args:
        given: the user's ``cfa`` (a layout, ``"none"``/``"mono"`` for explicitly
            monochrome, or None for not given).
        format_cfa: the pixel format's colour filter at the sensor's origin (``"RGGB"``...),
            None for a monochrome format.
        format_name: the pixel format's name, or None when the source cannot tell
            (image files): the user's word then stands.
        offset: (rows, cols) by which to shift the format's layout, for a source whose
            format names the colour filter at the sensor's origin rather than at the
            delivered frame's. GigE Vision and V4L2 formats name the first delivered
            pixel (PFNC; cameras keep colour regions at even offsets or rename the
            format), so they pass (0, 0).

    A contradiction is refused with a one-line error naming the fix: a Bayer format
    reconstructed as monochrome, a colour filter for a monochrome format, or a
    2x2 Bayer phase other than the format's. A larger layout (``quad-RGGB``) may
    refine a Bayer format, which has no PFNC name of its own.
    """
    mono = isinstance(given, str) and given.strip().lower() in MONO_WORDS
    user = None if given is None or mono else ColourFilter.parse(given)
    if format_name is None:
        return user
    if format_cfa is None:
        if user is not None:
            raise SveliveError(f"{where}: the camera delivers {format_name}, a monochrome format, but a colour "
                               f"filter ({user.name}) was given: drop --cfa, or choose a Bayer pixel format")
        return None
    native = ColourFilter.parse(format_cfa).shifted(*offset)
    if mono:
        raise SveliveError(f"{where}: the camera delivers {format_name}, a Bayer format (colour filter "
                           f"{native.name}), which cannot be reconstructed as monochrome: drop --cfa {given}, "
                           "or choose a Mono pixel format")
    if user is None or user == native:
        return native
    if user.is_bayer():
        raise SveliveError(f"{where}: the camera delivers {format_name} (colour filter {native.name} at this "
                           f"region), but --cfa {user.name} was given: drop --cfa")
    return user


@dataclass
class AfterChange:
    """Which frames show a setting a camera just applied (a new exposure time).

    A frame shows it when it was captured after ``changed_ns`` (monotonic ns, taken once the
    camera accepted the change) and it is at least the ``settle``-th frame (by frame id) after the
    first such frame: a frame in flight at the change may have been exposed before it. Used by
    ``svelive record --exposure-times`` and by the service's calibration sweep alike.
    """

    changed_ns: int
    settle: int = 1
    _first_id: int | None = field(default=None, init=False, repr=False)

    def shows(self, frame: Frame) -> bool:
        """True when ``frame`` (frames in capture order; the newest only, or every one) shows the change."""
        if frame.host_time_ns <= self.changed_ns:
            return False
        if self._first_id is None or frame.frame_id < self._first_id:  # first, or ids restarted (a new source)
            self._first_id = frame.frame_id
        return frame.frame_id >= self._first_id + self.settle


class EndOfStream(Exception):
    """Raised by ``Source._next`` when a finite source has no more frames."""


class Source:
    """Base class of the frame sources (GigE, V4L2, image sequences, replay, demo).

    Attributes:
        spec: the spec string this source was opened from (e.g. ``"gige:GV01"``).
        camera: the description attached to every frame it yields (svelive.Camera);
            final once the source is open (the pixel format and bit depth may only be
            known then).
        poll_s: longest time ``_next`` blocks before returning None.
    """

    poll_s: float = 0.1

    def __init__(self, spec: str, *, pattern: str | None = None, sensor: Sensor | None = None,
                 cfa: str | None = None) -> None:
        self.spec = spec
        mono = isinstance(cfa, str) and cfa.strip().lower() in MONO_WORDS
        self.camera = Camera.build(pattern, None if mono else cfa, sensor if sensor is not None else Sensor())
        if mono and self.camera.cfa is not None:
            raise SveliveError(f"{spec}: the layout {pattern} has the colour filter {self.camera.cfa.name}, but "
                               f"--cfa {cfa} was given: drop --cfa, or give the exposure pattern itself")
        # what the user asked for, directly or through a colour layout, to reconcile with the pixel format
        self._given_cfa: str | ColourFilter | None = cfa if mono else self.camera.cfa
        self._closing = threading.Event()
        self._lock = threading.Lock()
        self._opened = False
        self._ended = False
        self._online = False
        self._delivered = 0
        self._drops: dict[str, int] = {}
        self._recent: collections.deque[int] = collections.deque(maxlen=64)
        self._last: Frame | None = None
        self._error: str | None = None
        self._reconnects = 0

    @property
    def pattern(self) -> str | None:
        """The exposure pattern's text form when known (demo, replay, or given by the user), else None."""
        return None if self.camera.pattern is None else str(self.camera.pattern)

    @property
    def sensor(self) -> Sensor:
        """The sensor metadata of the frames it yields."""
        return self.camera.sensor

    def _settle_camera(self, sensor: Sensor, format_cfa: str | None = None, format_name: str | None = None) -> None:
        """Fix the camera once the device is known: its sensor, and the colour filter the user
        gave reconciled with the pixel format's (:func:`resolve_cfa`)."""
        cfa = resolve_cfa(self._given_cfa, format_cfa, format_name, where=self.spec)
        self.camera = self.camera.replace(sensor=sensor, cfa=cfa)

    # ----- exposure control ----------------------------------------------
    def exposure_time(self) -> float | None:
        """The camera's global exposure time in its own unit (GigE: microseconds), or None when
        the source cannot tell (files, replay, a camera without the control)."""
        return None

    def set_exposure_time(self, value: float) -> float:
        """Set the camera's global exposure time (same unit as :meth:`exposure_time`); returns the
        value the camera applied (it may round). Sources without the control raise SveliveError."""
        raise SveliveError(f"source {self.spec} cannot set its exposure time")

    def check_exposure_times(self, values: list[float]) -> None:
        """Raise a one-line SveliveError when :meth:`set_exposure_time` could not take one of
        ``values``, before anything is changed. A camera takes any time (it clamps or rounds, and
        reports what it applied), so the default accepts them all, unless the source checks a
        value with a ``_check_exposure(value)`` of its own (the demo: its range), which is asked
        for each of them."""
        check = getattr(self, "_check_exposure", None)
        if check is None:
            return
        for value in values:
            check(float(value))

    # ----- lifecycle ---------------------------------------------------
    def resume_after(self, frame: Frame) -> None:
        """Go on after ``frame``, the last frame a source of the same spec delivered before it was
        rebuilt (the service reopens a source that failed). Called once, after :meth:`open`. A live
        source has nothing to do; a finite one (replay) continues after that frame instead of from
        its start, with frame ids that keep increasing."""

    def open(self) -> Source:
        """Connect to the source and start it. Idempotent; returns self."""
        if self._closing.is_set():
            raise SveliveError(f"{self.spec}: source was closed; open a new one")
        if not self._opened:
            self._open()
            self._opened = True
            self._set_online(True)
        return self

    def close(self) -> None:
        """Stop the source and release it. Idempotent, callable from any thread."""
        self._closing.set()
        with self._lock:
            if not self._opened:
                return
            self._opened = False
        try:
            self._close()
        finally:
            self._set_online(False)

    @property
    def closed(self) -> bool:
        """True once close() was called."""
        return self._closing.is_set()

    def __enter__(self) -> Source:
        return self.open()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __iter__(self) -> Iterator[Frame]:
        """Frames until the source ends or is closed (from any thread)."""
        return self.frames()

    def frames(self, limit: int | None = None, seconds: float | None = None) -> Iterator[Frame]:
        """Iterate at most ``limit`` frames and for at most ``seconds`` (None: no limit).

        The time limit holds even while no frame comes (the wait is checked every ``poll_s``).
        """
        deadline = None if seconds is None else time.monotonic() + seconds
        n = 0
        self.open()
        while limit is None or n < limit:
            if deadline is not None and time.monotonic() >= deadline:
                return
            frame = self._poll()
            if frame is None:
                if self._ended or self._closing.is_set():
                    return
                continue
            n += 1
            yield frame

    def _poll(self) -> Frame | None:
        """One call of _next with end and close handling; the frame is counted as delivered."""
        if self._closing.is_set():
            return None
        try:
            frame = self._next()
        except EndOfStream:
            self._ended = True
            return None
        except Exception:
            if self._closing.is_set():  # the device went away under a close(): not an error
                return None
            raise
        if frame is None or self._closing.is_set():
            return None
        self._deliver(frame)
        return frame

    def read(self, timeout: float = 5.0) -> Frame:
        """The next frame; raises SveliveError when none comes within ``timeout`` seconds."""
        for frame in self.frames(limit=1, seconds=timeout):
            return frame
        if self._ended:
            raise SveliveError(f"{self.spec}: end of stream")
        raise SveliveError(f"{self.spec}: no frame within {timeout:g} s")

    # ----- statistics --------------------------------------------------
    def stats(self) -> dict[str, Any]:
        """Counters and state, a JSON-ready dict.

        Keys: ``source`` (spec), ``state`` ("online", "offline", "ended", "closed"),
        ``online`` (bool), ``frames`` (delivered), ``drops`` ({cause: count}),
        ``dropped`` (total), ``fps`` (delivery rate over the last frames, 0 when
        stalled), ``width``, ``height``, ``pixel_format``, ``last_frame_id``,
        ``reconnects``, ``error`` (last error text or None), ``cfa`` (colour filter
        name or None), plus source-specific keys from ``_extra_stats()``.
        """
        with self._lock:
            recent = list(self._recent)
            drops = dict(self._drops)
            last = self._last
            delivered = self._delivered
        now = time.monotonic_ns()
        fps = 0.0
        if len(recent) >= 2:
            span = recent[-1] - recent[0]
            idle = now - recent[-1]
            if span > 0 and idle < max(2e9, 3 * span / (len(recent) - 1)):
                fps = (len(recent) - 1) / (span / 1e9)
        if self._closing.is_set():
            state = "closed"
        elif self._ended:
            state = "ended"
        else:
            state = "online" if self._online else "offline"
        out: dict[str, Any] = {
            "source": self.spec, "state": state, "online": self._online and state == "online",
            "frames": delivered, "drops": drops, "dropped": sum(drops.values()), "fps": round(fps, 3),
            "width": None if last is None else int(last.raw.shape[1]),
            "height": None if last is None else int(last.raw.shape[0]),
            "pixel_format": None if last is None else last.pixel_format,
            "last_frame_id": None if last is None else last.frame_id,
            "reconnects": self._reconnects, "error": self._error,
            "cfa": None if self.camera.cfa is None else self.camera.cfa.name,
        }
        out.update(self._extra_stats())
        return out

    # ----- for subclasses ----------------------------------------------
    def _open(self) -> None:
        """Acquire the device or files; raise SveliveError with a one-line reason."""

    def _close(self) -> None:
        """Release what _open acquired. Called once, possibly from another thread."""

    def _next(self) -> Frame | None:
        """The next frame, None when none is ready within about ``poll_s``, or raise EndOfStream."""
        raise NotImplementedError

    def _extra_stats(self) -> dict[str, Any]:
        """Source-specific statistics merged into stats()."""
        return {}

    def _drop(self, cause: str, n: int = 1) -> None:
        with self._lock:
            self._drops[cause] = self._drops.get(cause, 0) + n

    def _set_online(self, online: bool, error: str | None = None) -> None:
        self._online = online
        if error is not None:
            self._error = error

    def _wait(self, seconds: float) -> bool:
        """Sleep up to ``seconds`` unless closed meanwhile; True when the source is still open."""
        if seconds > 0:
            return not self._closing.wait(seconds)
        return not self._closing.is_set()

    def _deliver(self, frame: Frame) -> None:
        with self._lock:
            self._delivered += 1
            self._recent.append(time.monotonic_ns())
            self._last = frame
