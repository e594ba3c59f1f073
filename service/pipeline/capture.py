"""The capture stage: opens the source, hands every frame to the reconstruction, reopens it when it fails."""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

from service.pipeline.config import FALLBACK_PATTERN, PipelineConfig
from service.pipeline.handoff import NewestSlot
from service.pipeline.meters import DropCounter, RateMeter
from svelive.capture import Source
from svelive.core.camera import Camera
from svelive.core.frame import Frame


class CaptureStage:
    """The capture thread's loop and what it knows of the source.

    ``factory`` builds a new (unopened) Source each time the stage (re)connects.
    Every frame goes into ``slot``, its camera given FALLBACK_PATTERN when the
    source knows no pattern; a frame pushed out unread counts as a
    ``reconstruct_busy`` drop.
    """

    def __init__(self, config: PipelineConfig, factory: Callable[[], Source], slot: NewestSlot,
                 drops: DropCounter, stop: threading.Event) -> None:
        self.config = config
        self._factory = factory
        self._slot = slot
        self._drops = drops
        self._stop = stop
        self._source: Source | None = None
        self.state = "starting"
        self._error: str | None = None
        self._stats: dict[str, Any] = {}
        self._closed_source_drops: collections.Counter = collections.Counter()
        #: reconnections: reopened sources after the first opened, plus the sources' own (GigE reconnects inside)
        self._reopens = 0
        self._closed_source_reconnects = 0
        #: the camera of the open source's frames, None before the first
        self.camera: Camera | None = None
        self._started_ns = time.monotonic_ns()
        self._run_ns: int | None = None  # when the capture thread started (after the kernels' warm-up)
        self._last_frame_ns: int | None = None
        self._online_since_ns: int | None = None
        self._newest_raw: Frame | None = None
        self.captured = RateMeter()

    def run(self) -> None:
        """The capture thread: until ``stop`` is set."""
        self._run_ns = time.monotonic_ns()
        opened = 0
        gap_ns = int(self.config.offline_after_s * 1e9)
        while not self._stop.is_set():
            source: Source | None = None
            try:
                source = self._factory()
                self._source = source
                if self._stop.is_set():
                    break
                source.open()
                if self._newest_raw is not None:  # a rebuilt source goes on where the last one stopped
                    source.resume_after(self._newest_raw)
                self._reopens += opened > 0
                opened += 1
                self.state, self._error = "online", None
                given: Camera | None = None
                for frame in source:
                    if frame.camera is not given:  # once per source camera, not per frame
                        given = frame.camera
                        self.camera = given if given.pattern is not None else given.with_pattern(FALLBACK_PATTERN)
                    if self.camera is not given:
                        frame = replace(frame, camera=self.camera)
                    self.captured.tick(frame.host_time_ns)
                    if self._last_frame_ns is None or frame.host_time_ns - self._last_frame_ns > gap_ns:
                        self._online_since_ns = frame.host_time_ns
                    self._last_frame_ns = frame.host_time_ns
                    self._newest_raw = frame
                    if self._slot.put(frame):
                        self._drops.count("reconstruct_busy")
                if self._stop.is_set():
                    break
                self._stats = source.stats()
                if self._stats.get("state") == "ended":
                    self.state = "ended"
                    return
                self.state = "offline"
                self._error = self._stats.get("error") or "the source stopped delivering"
            except Exception as exc:  # a camera that fails or vanishes: report, retry
                self.state = "offline"
                self._error = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            finally:
                if source is not None:
                    self._source = None
                    try:
                        self._stats = source.stats()
                    except Exception:
                        pass
                    source.close()
                    self._closed_source_drops.update(self._stats.get("drops", {}))
                    self._closed_source_reconnects += int(self._stats.get("reconnects") or 0)
                    self._stats = {**self._stats, "drops": {}, "reconnects": 0}
            self._stop.wait(self.config.retry_s)

    @property
    def stats(self) -> dict[str, Any]:
        """The open source's statistics now (``Source.stats()``), or the last source's; ``reconnects``
        counts every reconnection since the stage started (sources reopened and the sources' own)."""
        source = self._source
        stats = self._stats
        if source is not None:
            try:
                stats = source.stats()
            except Exception:  # noqa: BLE001 - a source closing under us: its last stats stand
                pass
        return {**stats, "reconnects": self.reconnects(stats)}

    def reconnects(self, stats: dict[str, Any] | None = None) -> int:
        """Reconnections since the stage started: sources reopened, plus those inside the sources."""
        stats = self._stats if stats is None else stats
        return self._reopens + self._closed_source_reconnects + int(stats.get("reconnects") or 0)

    @property
    def error(self) -> str | None:
        """Why the source is offline (one line), None while it is online."""
        return self.status()["error"]

    @property
    def source(self) -> Source | None:
        """The open source, None between connections."""
        return self._source

    def status(self) -> dict[str, Any]:
        """The source's state for /api/state: ``state`` (online, offline, ended), ``online``,
        ``error`` (why it is offline, one line; None while online), ``since`` (Unix time of the last
        change: the first frame of the current run of frames, or the last frame before an outage, or
        the start), ``for_s`` (seconds since then), ``reconnects``."""
        stats = self.stats
        now_ns = time.monotonic_ns()
        online = self.online(stats)
        if online:
            state, error, since_ns = "online", None, self._online_since_ns
        else:
            state = "ended" if self.state == "ended" else "offline"
            since_ns = self._last_frame_ns if self._last_frame_ns is not None else self._started_ns
            error = self._offline_reason(stats, now_ns) if state != "ended" else None
        since_ns = self._started_ns if since_ns is None else since_ns
        return {"state": state, "online": online, "error": error,
                "since": round(time.time() - (now_ns - since_ns) / 1e9, 3),
                "for_s": round((now_ns - since_ns) / 1e9, 1), "reconnects": stats["reconnects"]}

    def _offline_reason(self, stats: dict[str, Any], now_ns: int) -> str:
        """One line: the source's own reason, the stage's last exception, or how long no frame came."""
        if self._source is not None and stats.get("error") and stats.get("state") == "offline":
            return str(stats["error"]).splitlines()[0]
        if self._error:
            return self._error
        if self._last_frame_ns is None:
            return "connecting" if self.state == "starting" else "no frame yet"
        return f"no frame for {(now_ns - self._last_frame_ns) / 1e9:.1f} s"

    def close_source(self, timeout: float = 0.5) -> None:
        """Close the open source, if any (safe from any thread): ends the iteration in ``run``.

        Waits at most ``timeout`` seconds: a camera that vanished can block its driver's teardown
        for seconds (GigE: every command to it times out); the close then goes on in a daemon thread.
        """
        source = self._source
        if source is not None:
            closer = threading.Thread(target=source.close, name="svelive-close-source", daemon=True)
            closer.start()
            closer.join(timeout)

    def online(self, stats: dict[str, Any] | None = None) -> bool:
        """True while a source is connected and delivered a frame within ``offline_after_s``."""
        if self.state != "online" or self._last_frame_ns is None:
            return False
        if (time.monotonic_ns() - self._last_frame_ns) / 1e9 > self.config.offline_after_s:
            return False
        stats = self.stats if stats is None else stats
        return stats.get("online") is not False

    def awaiting_first_frame(self) -> bool:
        """True from the capture thread's start until its source delivers a first frame, fails, or
        ``offline_after_s`` passes without one (then it is offline)."""
        if self._run_ns is None or self._last_frame_ns is not None or self.state not in ("starting", "online"):
            return False
        return (time.monotonic_ns() - self._run_ns) / 1e9 <= self.config.offline_after_s

    def latest_raw(self) -> Frame | None:
        """The newest captured raw frame (with its camera), or None before the first."""
        return self._newest_raw

    def source_drops(self) -> collections.Counter:
        """Frames the sources dropped themselves, by cause, over every source opened so far."""
        drops = collections.Counter(self._closed_source_drops)
        drops.update(self.stats.get("drops", {}))
        return drops
