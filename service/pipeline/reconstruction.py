"""The reconstruction stage: takes the newest raw frame, reconstructs it, publishes the newest HdrFrame."""

from __future__ import annotations

import threading
import time

import numpy as np

from svelive.camera import Camera
from svelive.frame import Frame, HdrFrame
from svelive.reconstruction import Reconstructor

from service.pipeline.calibration import Calibration
from service.pipeline.frames import Published
from service.pipeline.meters import DropCounter, LatencyWindow, NewestSlot, RateMeter
from service.pipeline.noise import NoiseStage


class ReconstructionStage:
    """The reconstruction thread's loop and the newest frame it published.

    Takes Frames from ``slot``, gives each the calibration's camera (response and
    per-pixel map, :meth:`Calibration.apply`), reconstructs it with a
    ``svelive.Reconstructor`` for that camera (temporal fusion, motion mask; a new
    one when the camera, method or fusion setting changes) and publishes each
    result as the newest :class:`Published`, under ``cond``, which it notifies (the
    encoder waits on it). ``method`` may be changed at run time (under ``cond``).
    The confidence map is not computed: nothing in the live path reads it, and at
    1920x1200 it costs several ms per frame. A camera whose gain or read noise is
    unknown gets them from ``noise`` (:class:`NoiseStage`, its own thread), which
    this loop feeds with the frames and motion masks it made.
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
        self.noise = NoiseStage(stop)

    def latest(self) -> Published | None:
        """The newest reconstructed frame (an immutable record), or None before the first."""
        return self._latest

    def _reconstructor(self, current: tuple[tuple, Reconstructor] | None, camera: Camera,
                       method: str | None) -> tuple[tuple, Reconstructor]:
        """The reconstructor for this camera and method: the current one, or a new one (the old one closed)."""
        key = (camera, method, self.temporal)
        if current is not None:
            if current[0] == key:
                return current
            current[1].close()
        return key, Reconstructor(camera, method=method, temporal=self.temporal, workers=self.workers)

    def run(self) -> None:
        """The reconstruction thread: until ``stop`` is set."""
        current: tuple[tuple, Reconstructor] | None = None
        seq = 0
        self.noise.start()
        try:
            while not self._stop.is_set():
                frame: Frame | None = self._slot.get(timeout=0.2)
                if frame is None:
                    continue
                start_ns = time.monotonic_ns()
                try:
                    calibrated = self._calibration.apply(frame.camera)
                    camera = self.noise.camera_for(calibrated)
                    current = self._reconstructor(current, camera, self.method)
                    result = current[1].process(frame.raw)
                except Exception as exc:
                    self.error = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                    self._drops.count("reconstruct_error")
                    if current is not None:
                        current[1].close()
                    current = None
                    continue
                done_ns = time.monotonic_ns()
                self.error = None
                timings = {"queue": (start_ns - frame.host_time_ns) / 1e6, "reconstruct": (done_ns - start_ns) / 1e6}
                hdr = HdrFrame(image=result.image, confidence=None, frame_id=frame.frame_id,
                               host_time_ns=frame.host_time_ns, device_time_ns=frame.device_time_ns,
                               method=result.method, motion=result.motion, timings_ms=timings, camera=camera)
                self.motion_fraction = float(np.count_nonzero(result.motion)) / result.motion.size
                self.noise.offer(frame, calibrated, result.motion)
                seq += 1
                published = Published(hdr, seq, done_ns)
                self.reconstructed.tick(done_ns)
                self.latency["queue"].add(timings["queue"])
                self.latency["reconstruct"].add(timings["reconstruct"])
                self.latency["arrival_to_hdr"].add((done_ns - frame.host_time_ns) / 1e6)
                with self._cond:
                    self._latest = published
                    self._cond.notify_all()
        finally:
            self.noise.join(0.5)
            if current is not None:
                current[1].close()
