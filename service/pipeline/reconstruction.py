"""The reconstruction stage: takes the newest raw frame, reconstructs it, publishes the newest HdrFrame."""

from __future__ import annotations

import threading
import time

import numpy as np

from svelive.calibrate import Response, linearise
from svelive.frame import Frame, HdrFrame
from svelive.pattern import Pattern
from svelive.sensor import Sensor

from service.pipeline.calibration import Calibration
from service.pipeline.frames import Published
from service.pipeline.meters import DropCounter, LatencyWindow, NewestSlot, RateMeter


class FrameReconstructor:
    """The one adapter between the pipeline and the reconstruction library.

    Linearises raw frames through a calibrated response when there is one
    (``svelive.calibrate.linearise``), then runs the stateful
    ``svelive.reconstructor.Reconstructor`` (temporal fusion, motion mask).
    ``pattern`` may carry a calibrated per-pixel exposure map.
    """

    def __init__(self, pattern: Pattern, sensor: Sensor, method: str | None, temporal: bool,
                 response: Response | None = None, workers: int = 1) -> None:
        from svelive.reconstructor import Reconstructor

        self.pattern, self.sensor, self.method, self.temporal = pattern, sensor, method, temporal
        self.response = response
        self._stateful = Reconstructor(pattern, method=method, temporal=temporal, black_level=sensor.black_level,
                                       white_level=sensor.white_level, gain=sensor.gain,
                                       read_noise=sensor.read_noise, workers=workers)

    @property
    def name(self) -> str:
        """The method really in use (with temporal fusion the default differs; see svelive.reconstructor)."""
        return self._stateful.method

    def close(self) -> None:
        """Stop the reconstructor's worker threads."""
        self._stateful.close()

    def matches(self, pattern: Pattern, sensor: Sensor, method: str | None, temporal: bool,
                response: Response | None = None) -> bool:
        return (pattern, sensor, method, temporal) == (self.pattern, self.sensor, self.method, self.temporal) \
            and response is self.response

    def __call__(self, raw: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """(image float32 (H, W) radiance, None, motion bool (H, W)) of a raw frame.

        The confidence map (None here) is not computed: nothing in the service uses
        it, and at 1920x1200 it costs several ms per frame.
        """
        if self.response is not None:
            raw = linearise(raw, self.response, self.sensor)
        result = self._stateful.process(raw)
        return result.image, None, result.motion


class ReconstructionStage:
    """The reconstruction thread's loop and the newest frame it published.

    Takes (Frame, pattern text) items from ``slot``, reconstructs them through a
    FrameReconstructor (rebuilt when the pattern, sensor, method or response
    changes) and publishes each result as the newest :class:`Published`, under
    ``cond``, which it notifies (the encoder waits on it). ``method`` may be
    changed at run time (under ``cond``); the response and the pixel map come
    from ``calibration``.
    """

    def __init__(self, slot: NewestSlot, calibration: Calibration, method: str | None, temporal: bool, workers: int,
                 cond: threading.Condition, drops: DropCounter, stop: threading.Event) -> None:
        self._slot = slot
        self._calibration = calibration
        self.method = method
        self.temporal = temporal
        self.workers = workers
        self._cond = cond
        self._drops = drops
        self._stop = stop
        self._latest: Published | None = None
        self.motion_fraction: float | None = None
        self.error: str | None = None
        self.reconstructed = RateMeter()
        self.latency = {name: LatencyWindow() for name in ("queue", "reconstruct", "arrival_to_hdr")}

    def latest(self) -> Published | None:
        """The newest reconstructed frame (an immutable record), or None before the first."""
        return self._latest

    def run(self) -> None:
        """The reconstruction thread: until ``stop`` is set."""
        adapter: FrameReconstructor | None = None
        patterns: dict[str, Pattern] = {}  # one Pattern per text: a per-pixel map is compared by identity
        seq = 0
        try:
            while not self._stop.is_set():
                item = self._slot.get(timeout=0.2)
                if item is None:
                    continue
                frame, pattern_text = item
                frame: Frame
                start_ns = time.monotonic_ns()
                method, response = self.method, self._calibration.response
                try:
                    pattern = patterns.get(pattern_text)
                    if pattern is None:
                        pattern = Pattern.parse(pattern_text)
                        if self._calibration.pixel_map is not None:
                            pattern = pattern.with_pixel_map(self._calibration.pixel_map)
                        patterns = {pattern_text: pattern}
                    if adapter is None or not adapter.matches(pattern, frame.sensor, method, self.temporal, response):
                        if adapter is not None:
                            adapter.close()
                        adapter = FrameReconstructor(pattern, frame.sensor, method, self.temporal, response,
                                                     self.workers)
                    image, confidence, motion = adapter(frame.raw)
                except Exception as exc:
                    self.error = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                    self._drops.count("reconstruct_error")
                    if adapter is not None:
                        adapter.close()
                    adapter = None
                    continue
                done_ns = time.monotonic_ns()
                self.error = None
                timings = {"queue": (start_ns - frame.host_time_ns) / 1e6, "reconstruct": (done_ns - start_ns) / 1e6}
                hdr = HdrFrame(image=image, confidence=confidence, frame_id=frame.frame_id,
                               host_time_ns=frame.host_time_ns, device_time_ns=frame.device_time_ns,
                               method=adapter.name, motion=motion, timings_ms=timings)
                if motion is not None:
                    self.motion_fraction = float(np.count_nonzero(motion)) / motion.size
                seq += 1
                published = Published(hdr, seq, pattern_text, frame.sensor, done_ns)
                self.reconstructed.tick(done_ns)
                self.latency["queue"].add(timings["queue"])
                self.latency["reconstruct"].add(timings["reconstruct"])
                self.latency["arrival_to_hdr"].add((done_ns - frame.host_time_ns) / 1e6)
                with self._cond:
                    self._latest = published
                    self._cond.notify_all()
        finally:
            if adapter is not None:
                adapter.close()
