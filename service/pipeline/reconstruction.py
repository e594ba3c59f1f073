"""The reconstruction stage: takes the newest raw frames, reconstructs them (several at once), publishes the
newest HdrFrame."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np

from service.pipeline.calibration import Calibration
from service.pipeline.frames import Published
from service.pipeline.handoff import Newest, NewestSlot
from service.pipeline.meters import DropCounter, LatencyWindow, RateMeter
from service.pipeline.quality import LiveQuality, LiveStep
from svelive.core.camera import Camera
from svelive.core.frame import Frame, HdrFrame
from svelive.reconstruction import Reconstructor
from svelive.reconstruction.single import confidence_from_variance
from svelive.reconstruction.stream import Estimated, SequenceResult


class ReconstructionStage:
    """The reconstruction threads' loop and the newest frame they published.

    Takes Frames from ``slot``, gives each the calibration's camera (response and
    per-pixel map, :meth:`Calibration.apply`), reconstructs it with a
    ``svelive.Reconstructor`` for that camera (temporal fusion, motion mask; a new
    one when the camera, method or fusion setting changes) and publishes each
    result as the newest :class:`Published` of ``hdr_port`` (the encoder and the snapshots read it). The method and fusion setting are the live-quality ladder's
    current step (``quality``, :class:`LiveQuality`), which every published frame feeds
    with the camera's arrivals (``captured``) and the frames dropped while it was busy;
    ``LiveQuality.configure`` changes the configured method at run time.

    ``refresh`` (K, ``PipelineConfig.refresh``) is every stream's ``Reconstructor(refresh=K, colour_refresh=True)``:
    a stream with fusion and ``adaptive``, monochrome or colour (the bands of its folded luminance), runs the
    method per frame only on the bands whose history needs it and a round-robin 1 / K of the settled ones, once its
    noise model is trusted (other streams ignore it); which bands run is decided when a frame is fused, so
    ``frames`` > 1 gives the same frames.

    ``frames`` threads each take the next frame and make its history-free part
    (``Reconstructor.estimate``, spread over ``workers // frames`` strip threads), then
    fuse and publish it when every frame taken before it has been
    (``Reconstructor.fuse``, in arrival order). One frame at a time over every
    thread has the lowest latency; whole frames in parallel waste less on the strips'
    hand-offs (on 2 cores, no viewer: 12.0 against 9.8 fps) but each frame takes one
    thread's time (with 10 MJPEG viewers: 8.2 against 7.8 fps, latency p95 443
    against 252 ms), so the default is one (docs/service.md).

    The confidence map is made only when asked (a pixel read-out, the confidence overlay, an
    EXR snapshot with its channel: ``HdrFrame.confidence_map``), once per frame: at 1920x1200 it
    costs several ms, and most frames are never asked. A camera whose gain or read noise is
    unknown gets them as a library stream does (``svelive.Reconstructor``'s own model,
    svelive.noise.StreamNoise: the first frame's estimate, refined from the static pixels of
    runs of frames, fusion only once it is trusted), with the fits on the stream's noise thread;
    a stream that replaces another of the same camera (a live-quality step) goes on from its
    model (``Reconstructor.continue_noise``).
    """

    def __init__(self, slot: NewestSlot, calibration: Calibration, quality: LiveQuality, captured: RateMeter,
                 workers: int, hdr_port: Newest[Published], drops: DropCounter, stop: threading.Event,
                 frames: int = 1, refresh: int = 0) -> None:
        self._slot = slot
        self._calibration = calibration
        self.quality = quality
        self._captured = captured
        self.workers = workers
        self.frames = frames
        self.refresh = refresh  # Reconstructor(refresh=...): streams with fusion skip settled bands
        #: the newest reconstructed frame; its sequence number is the frame's ``Published.seq``
        self.hdr_port = hdr_port
        self._drops = drops
        self._stop = stop
        self.motion_fraction: float | None = None
        self.error: str | None = None
        self.reconstructed = RateMeter()
        self.latency = {name: LatencyWindow() for name in ("queue", "reconstruct", "arrival_to_hdr")}
        self._take = threading.Lock()  # taking a frame, its ticket and its stream
        self._turn = threading.Condition()  # whose ticket fuses and publishes next
        self._tickets = 0  # given out
        self._next = 0  # the ticket whose turn it is
        self._current: tuple[tuple, Reconstructor] | None = None

    def latest(self) -> Published | None:
        """The newest reconstructed frame (an immutable record), or None before the first."""
        return self.hdr_port.latest()

    def _reconstructor(self, camera: Camera, step: LiveStep) -> Reconstructor:
        """The reconstructor for this camera and live step: the current one, or a new one (the old one closed).
        Called under ``_take``."""
        key = (camera, step)
        previous = None
        if self._current is not None:
            if self._current[0] == key:
                return self._current[1]
            previous = self._current[1]
        stream = Reconstructor(camera, method=step.method, temporal=step.temporal,
                               workers=max(1, self.workers // self.frames), noise_thread=True, refresh=self.refresh,
                               colour_refresh=True)
        if previous is not None:
            if self._current[0][0] == camera:
                stream.continue_noise(previous)
            previous.close()
        self._current = key, stream
        return stream

    def noise_state(self) -> dict | None:
        """For /api/state: the noise model the current stream estimates (``Reconstructor.noise_state``), None
        when the camera gives its own."""
        current = self._current
        return None if current is None else current[1].noise_state()

    def refresh_state(self) -> dict | None:
        """For /api/state: the current stream's band refresh (``Reconstructor.refresh_state``), None when off."""
        current = self._current
        return None if current is None else current[1].refresh_state()

    def _failed(self, exc: BaseException, stream: Reconstructor | None) -> None:
        """A frame could not be reconstructed: say why, count it, and start the stream afresh."""
        self.error = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        self._drops.count("reconstruct_error")
        with self._take:
            if self._current is not None and self._current[1] is stream:
                stream.close()
                self._current = None

    def run(self) -> None:
        """The reconstruction threads (this one and ``frames - 1`` more): until ``stop`` is set."""
        others = [threading.Thread(target=self._loop, name=f"svelive-reconstruct-{i + 1}", daemon=True)
                  for i in range(self.frames - 1)]
        for thread in others:
            thread.start()
        try:
            self._loop()
        finally:
            for thread in others:
                thread.join(5.0)
            if self._current is not None:
                self._current[1].close()

    def _loop(self) -> None:
        while not self._stop.is_set():
            stream: Reconstructor | None = None
            with self._take:
                frame: Frame | None = self._slot.get(timeout=0.2)
                if frame is None:
                    continue
                ticket, self._tickets = self._tickets, self._tickets + 1
                start_ns = time.monotonic_ns()
                failure: BaseException | None = None
                step = self.quality.step
                try:
                    camera = self._calibration.apply(frame.camera)
                    stream = self._reconstructor(camera, step)
                except Exception as exc:
                    failure = exc
            estimated = None
            if failure is None:
                try:
                    estimated = stream.estimate(frame.raw)
                except Exception as exc:
                    failure = exc
            with self._turn:
                while self._next != ticket:  # the frames taken before this one fuse first
                    self._turn.wait(0.5)
                try:
                    result = None if failure is not None else stream.fuse(estimated)
                except Exception as exc:
                    failure = exc
                try:
                    if failure is not None:
                        self._failed(failure, stream)
                    else:
                        self._publish(frame, estimated, result, start_ns, step)
                finally:
                    self._next += 1
                    self._turn.notify_all()

    def _publish(self, frame: Frame, estimated: Estimated, result: SequenceResult, start_ns: int,
                 step: LiveStep) -> None:
        """Publish a reconstructed frame as the newest (called in arrival order), and tell the live quality."""
        done_ns = time.monotonic_ns()
        self.error = None
        timings = {"queue": (start_ns - frame.host_time_ns) / 1e6, "reconstruct": (done_ns - start_ns) / 1e6}
        hdr = HdrFrame(image=result.image, confidence=None, frame_id=frame.frame_id,
                       host_time_ns=frame.host_time_ns, device_time_ns=frame.device_time_ns,
                       method=result.method, motion=result.motion, timings_ms=timings, camera=estimated.camera,
                       confidence_of=_confidence_of(result))
        self.motion_fraction = result.moving_fraction
        published = Published(hdr, self.hdr_port.seq + 1, done_ns, estimated.noise)  # the only writer: the port's next number
        self.reconstructed.tick(done_ns)
        self.latency["queue"].add(timings["queue"])
        self.latency["reconstruct"].add(timings["reconstruct"])
        self.latency["arrival_to_hdr"].add((done_ns - frame.host_time_ns) / 1e6)
        self.hdr_port.put(published)
        self.quality.observe(done_ns, self._captured.count, self._drops.snapshot().get("reconstruct_busy", 0),
                             timings["reconstruct"], step, result.method_rows)


def _confidence_of(result: SequenceResult) -> Callable[[], np.ndarray]:
    """What makes ``result``'s confidence map when first asked, holding only what that needs (not the result)."""
    plane, variance_of, lower_bound = result.plane, result.variance_of, result.lower_bound
    return lambda: confidence_from_variance(plane, variance_of(), lower_bound)
