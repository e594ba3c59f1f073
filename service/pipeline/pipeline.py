"""The Pipeline: wires the capture, reconstruction and encoder stages of one source and reports their state."""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import cv2

from service.pipeline.calibration import Calibration
from service.pipeline.capture import CaptureStage
from service.pipeline.colour import ColourStage
from service.pipeline.config import PipelineConfig, check_jpeg_quality, check_method
from service.pipeline.encoder import EncoderStage
from service.pipeline.frames import EncodedFrame, PreviewFrame, Published
from service.pipeline.handoff import Newest, NewestSlot
from service.pipeline.meters import DropCounter
from service.pipeline.quality import LiveQuality
from service.pipeline.reconstruction import ReconstructionStage
from svelive.calibrate.response import SWEEP_KNOTS
from svelive.capture import Source
from svelive.core.errors import SveliveError
from svelive.core.frame import Frame
from svelive.reconstruction.stream import default_method


def _updated(settings: Any, changes: dict[str, Any] | None, what: str) -> Any:
    """A copy of the frozen dataclass ``settings`` with ``changes`` (validated by its constructor);
    an unknown name is a one-line SveliveError listing the accepted ones."""
    if not changes:
        return settings
    unknown = sorted(set(changes) - set(vars(settings)))
    if unknown:
        raise SveliveError(f"unknown {what} setting(s) {', '.join(unknown)}; accepted: {', '.join(vars(settings))}")
    return replace(settings, **changes)


def opencv_threads(cpu_count: int | None = None) -> int:
    """OpenCV pool size for the pipeline: the cores minus one, at least 1.

    The reconstruction thread and the encoder thread each run on a core of their
    own; OpenCV's parallel loops inside them would otherwise compete for the same
    cores (on 2 cores: 1 thread, i.e. no OpenCV pool at all).
    """
    return max(1, (cpu_count or os.cpu_count() or 1) - 1)


class Pipeline:
    """Runs the capture, reconstruction and encoder threads of one source.

    ``source_factory`` builds a new (unopened) Source each time the pipeline
    (re)connects; by default ``config.build_source``. The stages
    share a stop event, the drop counter and one condition (the newest
    reconstructed frame, the encoder's inputs and the run-time settings).

    Its ports, each a :class:`Newest` hand-off any publisher reads (and none is queued for):
    ``hdr_port`` the newest reconstructed frame (:class:`Published`; EXR snapshots, state),
    ``jpeg_port`` the newest preview JPEG (MJPEG, JPEG snapshots), ``preview_port`` the newest
    tone-mapped 8-bit preview while a preview watcher asks for them (RTSP). It makes no output of its
    own: MJPEG, RTSP, the snapshots and the state are publisher modules (``service.publishers``) over
    its ports and stages.
    """

    def __init__(self, config: PipelineConfig, source_factory: Callable[[], Source] | None = None) -> None:
        self.config = config
        self.workers = config.workers or os.cpu_count() or 1
        self._stop = threading.Event()
        self._slot = NewestSlot(config.queue)
        self._cond = threading.Condition()  # guards the newest frame and the settings, and wakes the encoder
        self.hdr_port: Newest[Published] = Newest(self._cond)
        self.drops = DropCounter()
        self.capture = CaptureStage(config, source_factory or config.build_source, self._slot, self.drops,
                                    self._stop)
        # the configured response and mask are read now, so a bad file fails before serving
        self.calibration = Calibration(config.response, config.mask, self.capture.latest_raw, self._stop)
        frames = min(config.parallel_frames, self.workers)
        self.quality = LiveQuality(config.method or default_method(config.temporal), config.temporal,
                                   config.live_quality, parallel=frames)
        self.reconstruction = ReconstructionStage(self._slot, self.calibration, self.quality, self.capture.captured,
                                                  self.workers, self.hdr_port, self.drops, self._stop, frames=frames,
                                                  refresh=config.refresh)
        #: white balance and output space, shared by the preview (JPEG, RTSP) and the EXR snapshot
        self.colour = ColourStage(config.colour)
        self.encoder = EncoderStage(config, self.hdr_port, self.capture.online, self._cond, self.drops, self._stop,
                                    self.colour)
        self.jpeg_port: Newest[EncodedFrame] = self.encoder.jpeg_port
        self.preview_port: Newest[PreviewFrame] = self.encoder.preview_port
        self.captured = self.capture.captured
        self.reconstructed = self.reconstruction.reconstructed
        self.encoded = self.encoder.encoded
        self.latency = {**self.reconstruction.latency, **self.encoder.latency}
        self._threads: list[threading.Thread] = []
        #: when the pipeline was made (``time.monotonic_ns``; the state's uptime)
        self.started_ns = time.monotonic_ns()
        #: the service prepares its kernels before it starts the threads (set by the app, cleared by :meth:`start`)
        self.warming_up = False

    # ----- lifecycle ---------------------------------------------------
    def start(self) -> Pipeline:
        """Start the three threads; returns self."""
        if self._threads:
            return self
        self.warming_up = False
        cv2.setNumThreads(opencv_threads())
        for name, target in (("capture", self.capture.run), ("reconstruct", self.reconstruction.run),
                             ("encode", self.encoder.run)):
            thread = threading.Thread(target=target, name=f"svelive-{name}", daemon=True)
            thread.start()
            self._threads.append(thread)
        return self

    def stop(self, timeout: float = 5.0) -> None:
        """Stop the threads and close the source (idempotent)."""
        self._stop.set()
        self.capture.close_source()
        self._slot.close()
        with self._cond:
            self._cond.notify_all()
        for thread in self._threads:
            thread.join(timeout)
        self._threads = []

    def __enter__(self) -> Pipeline:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


    # ----- the stages' own answers ---------------------------------------
    def online(self) -> bool:
        """True while a source is connected and delivered a frame within ``offline_after_s``."""
        return self.capture.online()

    def latest(self, wait_s: float = 0.0) -> Published | None:
        """The newest reconstructed frame (an immutable record), or None before the first; before the first, while
        the camera is starting (:meth:`readiness`), waits up to ``wait_s`` s for it (the first frame after start-up
        loads the kernels it needs and takes a second or two)."""
        latest = self.hdr_port.latest()
        if latest is None and wait_s > 0 and self.readiness() == "starting":
            newest = self.hdr_port.get_newest(0, wait_s)
            latest = None if newest is None else newest[1]
        return latest

    def readiness(self) -> str:
        """What /healthz says of this camera: "warming_up" (the kernels are being prepared), "starting" (the source
        is opening and has not failed, for up to ``offline_after_s``, or frames come and none is reconstructed yet:
        a snapshot would be refused), "offline" (no source delivers frames) or "online"."""
        if self.warming_up:
            return "warming_up"
        if not self.online():
            return "starting" if self.capture.awaiting_first_frame() else "offline"
        return "starting" if self.hdr_port.latest() is None else "online"

    def latest_raw(self) -> Frame | None:
        """The newest captured raw frame (with its camera), or None before the first."""
        return self.capture.latest_raw()

    def watch(self, delta: int) -> None:
        """Add (+1) or remove (-1) a JPEG stream client; JPEGs are made for ``jpeg_port`` only while there is one."""
        self.encoder.watch(delta)

    def watch_previews(self, delta: int) -> None:
        """Add (+1) or remove (-1) a preview consumer (RTSP with clients); previews are made for ``preview_port``
        only while there is one."""
        self.encoder.watch_previews(delta)

    def preview_size(self, width: int, height: int) -> tuple[int, int]:
        """(width, height) of the preview of a frame of ``width`` x ``height`` (scaled down to ``preview_width``)."""
        return self.encoder.preview_size(width, height)

    def latest_preview(self) -> PreviewFrame | None:
        """The newest tone-mapped preview of a reconstructed frame (never a no-signal one), or None."""
        return self.encoder.latest_preview()

    def snapshot_jpeg(self, timeout: float = 2.0) -> EncodedFrame | None:
        """A JPEG of the newest reconstructed frame, encoding it if nobody did; None if there is none."""
        return self.encoder.snapshot_jpeg(timeout)

    def start_sweep(self, times: list[float], max_degree: int = 6, apply: bool = False,
                    max_knots: int = SWEEP_KNOTS) -> dict[str, Any]:
        """Calibrate the response from frames at the exposure times ``times`` (a background job);
        see :meth:`service.pipeline.calibration.Calibration.start_sweep`. Returns the job."""
        # the capture stage's open source (it has no public accessor yet)
        return self.calibration.start_sweep(times, self.capture.source, max_degree, apply, max_knots=max_knots)

    def response_state(self) -> dict[str, Any] | None:
        """The response in use: origin (file path or "calibrated live"), degree, coefficients, domain; None if linear
        (:meth:`service.pipeline.calibration.Calibration.response_state`)."""
        return self.calibration.response_state()

    # ----- settings ----------------------------------------------------
    def settings(self) -> dict[str, Any]:
        """The settings that can be changed at run time."""
        return {"method": self.quality.configured.method, "jpeg_quality": self.encoder.jpeg_quality,
                "tone": dict(vars(self.encoder.tone)), **self.colour.public()}

    def update_settings(self, method: str | None = None, jpeg_quality: int | None = None,
                        tone: dict[str, float] | None = None, colour: dict[str, Any] | None = None) -> dict[str, Any]:
        """Change method, JPEG quality, tone mapping and colour output (all checked first); returns settings().

        ``colour``: any of ``white_balance``, ``colour_matrix`` (None removes it) and
        ``output_space`` (svelive.whitebalance.ColourSettings), checked together with the
        ones kept (rec709 needs a matrix).
        """
        check_method(method)
        if jpeg_quality is not None:
            check_jpeg_quality(jpeg_quality)
        new_tone = _updated(self.encoder.tone, tone, "tone mapping")
        new_colour = _updated(self.colour.settings, colour, "colour")
        with self._cond:
            if method is not None:
                self.quality.configure(method, self.config.temporal)
            if jpeg_quality is not None:
                self.encoder.jpeg_quality = int(jpeg_quality)
            self.encoder.tone = new_tone
            self.colour.settings = new_colour
            self._cond.notify_all()
        return self.settings()

    # ----- state -------------------------------------------------------
    def state(self) -> dict[str, Any]:
        """The pipeline's part of /api/state (``service.publishers.state.pipeline_state``, which assembles it)."""
        from service.publishers.state import pipeline_state  # the state publisher reads the pipeline

        return pipeline_state(self)
