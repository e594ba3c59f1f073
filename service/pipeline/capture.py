"""The capture stage: opens the source, hands every frame to the reconstruction, reopens it when it fails."""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

from svelive.camera import Camera
from svelive.capture import Source
from svelive.frame import Frame

from service.pipeline.config import FALLBACK_PATTERN, PipelineConfig
from service.pipeline.meters import DropCounter, NewestSlot, RateMeter


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
        self.error: str | None = None
        self.stats: dict[str, Any] = {}
        self._closed_source_drops: collections.Counter = collections.Counter()
        #: the camera of the open source's frames, None before the first
        self.camera: Camera | None = None
        self._last_frame_ns: int | None = None
        self._newest_raw: Frame | None = None
        self.captured = RateMeter()

    def run(self) -> None:
        """The capture thread: until ``stop`` is set."""
        while not self._stop.is_set():
            source: Source | None = None
            try:
                source = self._factory()
                self._source = source
                if self._stop.is_set():
                    break
                source.open()
                self.state, self.error = "online", None
                given: Camera | None = None
                for frame in source:
                    if frame.camera is not given:  # once per source camera, not per frame
                        given = frame.camera
                        self.camera = given if given.pattern is not None else given.with_pattern(FALLBACK_PATTERN)
                    if self.camera is not given:
                        frame = replace(frame, camera=self.camera)
                    self.captured.tick(frame.host_time_ns)
                    self._last_frame_ns = frame.host_time_ns
                    self._newest_raw = frame
                    if self._slot.put(frame):
                        self._drops.count("reconstruct_busy")
                    self.stats = source.stats()
                if self._stop.is_set():
                    break
                self.stats = source.stats()
                if self.stats.get("state") == "ended":
                    self.state = "ended"
                    return
                self.state = "offline"
            except Exception as exc:  # a camera that fails or vanishes: report, retry
                self.state = "offline"
                self.error = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            finally:
                if source is not None:
                    try:
                        self.stats = source.stats()
                    except Exception:
                        pass
                    source.close()
                    self._closed_source_drops.update(self.stats.get("drops", {}))
                    self.stats = {**self.stats, "drops": {}}
                self._source = None
            self._stop.wait(self.config.retry_s)

    def close_source(self) -> None:
        """Close the open source, if any (safe from any thread): ends the iteration in ``run``."""
        source = self._source
        if source is not None:
            source.close()

    def online(self) -> bool:
        """True while a source is connected and delivered a frame within ``offline_after_s``."""
        if self.state != "online" or self._last_frame_ns is None:
            return False
        if self.stats and self.stats.get("online") is False:
            return False
        return (time.monotonic_ns() - self._last_frame_ns) / 1e9 <= self.config.offline_after_s

    def latest_raw(self) -> Frame | None:
        """The newest captured raw frame (with its camera), or None before the first."""
        return self._newest_raw

    def source_drops(self) -> collections.Counter:
        """Frames the sources dropped themselves, by cause, over every source opened so far."""
        drops = collections.Counter(self._closed_source_drops)
        drops.update(self.stats.get("drops", {}))
        return drops
