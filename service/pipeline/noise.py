"""The live noise model: gain and read noise of a camera that was not told them, refined over the stream.

The reconstruction thread offers each frame it reconstructed (a reference, no copy);
every ``interval_s`` three consecutively reconstructed frames (frames dropped at the
hand-off between them do not matter) are handed to this stage's own
thread, which adds them to a :class:`svelive.noise.NoiseTracker` and fits its pool once: the first frame's
single-frame samples, and the differences of the pixels the motion tests found
static over the three (texture-free; the third frame groups them by signal without
the bias of grouping by their own noisy values, :func:`svelive.noise.triple_samples`).
The reconstruction uses the estimate once it has moved from the one in use by more than ``change`` (relative) and more than
its own standard error: every change starts a new Reconstructor, and so restarts
temporal fusion, so it must be rare.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass

import numpy as np

from service.pipeline.handoff import Newest
from svelive.core.camera import Camera
from svelive.core.frame import Frame
from svelive.noise import PRIOR_LOG_SIGMA, NoiseEstimate, NoiseTracker

#: consecutive frames per update of the tracker: three give texture-free samples without the pairs' binning bias
RUN_FRAMES = 3


@dataclass(frozen=True)
class _Run:
    """Consecutive frames of one camera, and for each after the first the pixels the motion tests found
    static in it (bool (H, W))."""
    frames: tuple[Frame, ...]
    static: tuple[np.ndarray, ...]
    camera: Camera


class NoiseStage:
    """A noise-model thread beside the reconstruction: :meth:`offer` frames, read :meth:`camera_for` and :meth:`state`."""

    def __init__(self, stop: threading.Event, interval_s: float = 5.0, change: float = 0.05) -> None:
        self._stop = stop
        self.interval_s = interval_s
        self.change = change
        self._tracker = NoiseTracker()
        #: the newest run offered (an older one not yet taken is skipped)
        self._runs: Newest[_Run] = Newest()
        self._recent: list[tuple[Frame, np.ndarray | None]] = []  # the newest consecutive frames, oldest first
        self._recent_camera: Camera | None = None
        self._last_offer = -math.inf
        self._estimate: NoiseEstimate | None = None
        self._applied: NoiseEstimate | None = None
        self._applied_key: Camera | None = None
        self.updates = 0
        self.error: str | None = None
        self._thread: threading.Thread | None = None

    @staticmethod
    def needed(camera: Camera) -> bool:
        """True when the camera's gain or read noise is unknown."""
        return camera.sensor.gain is None or camera.sensor.read_noise is None

    def camera_for(self, camera: Camera) -> Camera:
        """``camera`` with the estimate in use filled in where its sensor has no gain or read noise."""
        applied = self._applied
        if applied is None or not self.needed(camera) or self._applied_key != camera:
            return camera
        return camera.replace(sensor=applied.apply(camera.sensor))

    def offer(self, frame: Frame, camera: Camera, reset: np.ndarray | None) -> None:
        """The reconstruction thread, after each frame: ``camera`` as calibrated (before :meth:`camera_for`);
        ``reset``: bool (H, W), the pixels that did not keep their history (the stream's ``reset``), or None
        for a frame not fused with one."""
        if not self.needed(camera):
            self._recent = []
            return
        recent = self._recent
        # consecutive reconstructed frames, not ids: frames dropped at the hand-off between them do not
        # matter, as each frame's reset mask compares it with the fused history, which holds the last one
        if (not recent or self._recent_camera != camera or reset is None
                or frame.frame_id <= recent[-1][0].frame_id):
            recent = []
        recent = [*recent[-(RUN_FRAMES - 1):], (frame, None if reset is None else ~np.asarray(reset, bool))]
        self._recent, self._recent_camera = recent, camera
        now = time.monotonic()
        if len(recent) < RUN_FRAMES or now - self._last_offer < self.interval_s:
            return
        self._last_offer = now
        self._recent = []  # the next run starts afresh: no frame is handed over twice
        self._runs.put(_Run(tuple(f for f, _ in recent), tuple(m for _, m in recent[1:]), camera))

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="svelive-noise", daemon=True)
        self._thread.start()

    def join(self, timeout: float) -> None:
        self._runs.wake()
        if self._thread is not None:
            self._thread.join(timeout)

    def _run(self) -> None:
        taken = 0
        while not self._stop.is_set():
            got = self._runs.get_newest(taken, 0.5)
            if got is None:
                continue
            taken, run = got
            try:
                # only the run's last estimate is used: the pool is fitted once per run, not per frame
                self._tracker.add(run.frames[0].raw, run.camera)
                for frame, static in zip(run.frames[1:], run.static):
                    self._tracker.add(frame.raw, run.camera, static)
                estimate = self._tracker.fit()
            except Exception as exc:  # a frame the estimator cannot use: say so, keep the estimate in use
                self.error = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                continue
            self.error = None
            self.updates += 1
            self._estimate = estimate
            if self._applied_key != run.camera or self._moved(estimate, self._applied):
                self._applied, self._applied_key = estimate, run.camera

    def _moved(self, new: NoiseEstimate, old: NoiseEstimate | None) -> bool:
        if old is None:
            return True
        for value, before, sigma in ((new.gain, old.gain, new.gain_sigma),
                                     (new.read_noise, old.read_noise, new.read_noise_sigma)):
            step = abs(value - before)
            if step > self.change * max(abs(before), 1e-9) and step > (sigma or 0.0):
                return True
        return False

    def model_of(self, used: Camera) -> NoiseEstimate:
        """The noise model a published frame's camera ``used`` was reconstructed with: the estimate in use,
        the sensor's given values, or the fixed defaults (for EXR attributes)."""
        applied, sensor = self._applied, used.sensor
        if applied is not None and (sensor.gain, sensor.read_noise) == (applied.gain, applied.read_noise):
            return applied
        if sensor.gain is not None and sensor.read_noise is not None:
            return NoiseEstimate.given(sensor)
        # the defaults are a guess: stated with the prior's uncertainty, as the library states them
        return NoiseEstimate(sensor.effective_gain, sensor.effective_read_noise,
                             PRIOR_LOG_SIGMA * sensor.effective_gain, PRIOR_LOG_SIGMA * sensor.effective_read_noise,
                             0, "default")

    def state(self) -> dict | None:
        """For /api/state: the newest estimate, the one in use, and how many runs of consecutive frames made
        it; None when the camera's noise model is given (or before the first estimate)."""
        estimate, applied = self._estimate, self._applied
        if estimate is None:
            return None
        return {**estimate.to_dict(), "in_use": None if applied is None else applied.to_dict(),
                "runs": self.updates, "error": self.error}
