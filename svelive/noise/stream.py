"""One stream's noise model, what svelive.Reconstructor, stream_noise and reprocessing share: when a stream
refines it and when it is trusted (:class:`NoiseSchedule`, :class:`StreamNoise`)."""

from __future__ import annotations

import threading
from concurrent.futures import Executor
from dataclasses import dataclass
from functools import partial
from typing import TYPE_CHECKING

import numpy as np

from svelive.core.errors import SveliveError
from svelive.noise.frame import estimate_from_frame
from svelive.noise.model import NoiseEstimate, agree, variance_uncertainty
from svelive.noise.tracker import NoiseTracker

if TYPE_CHECKING:  # the Camera is only read here (its pattern, colour filter and sensor)
    from svelive.core.camera import Camera


@dataclass(frozen=True)
class NoiseSchedule:
    """When a stream refines its noise model, and when the model is trusted (:class:`StreamNoise`).

    Attributes:
        run_frames: consecutive frames per run of the tracker (3: the first frame's single-frame
            samples, then the static pixels' differences over the next two, as the service's runs).
        refit_every: frames from the start of one run to the start of the next; 0 stops after the
            first complete run. The tracker is fitted after the second and the last frame of the
            first run, then once per run (about 250 ms CPU per fit at 1920x1200). While the model is
            not trusted the runs come sooner: 0, 3, 9, 21, ... frames apart (StreamNoise).
        trusted_below: the model is trusted (fusion may change the output) once a fit with temporal
            samples states the modelled variance to within this relative standard uncertainty at
            every signal (:func:`variance_uncertainty`). At 0.15 a variance one standard uncertainty
            low leaves the fusion's 3-sigma detail test at 3 sqrt(0.85) = 2.77 sigma and its 4-sigma
            motion test at 3.7 sigma: the share of noise taken for detail or motion at most doubles
            (0.27 % -> 0.56 %, 6e-5 -> 2e-4), where the fixed defaults can be several times off.
        refit_max: the longest gap, in frames from run start to run start, that the schedule backs off to
            while the model is trusted and each later run's fit agrees with it (:func:`agree`): the gap doubles
            from ``refit_every`` with each agreeing fit, and is ``refit_every`` again after a fit that
            disagrees (or leaves the model untrusted), and for a new model (a camera change makes a new
            :class:`StreamNoise`). What the service changes itself does not need a refit to be seen: the
            gain is set only when the camera is opened, an exposure time change does not change the model
            (gain and read noise in DN), and a new calibration or pixel format is a new camera, hence a new
            model (``Reconstructor._with_noise``). What is left changes slowly: the sensor's temperature
            (read noise, dark signal) over a warm-up of minutes. 512 frames is 17 s at 30 fps and 26 s at the
            service's 20 fps, well within that; a fit costs about 250 ms CPU at 1920x1200, so the noise thread
            goes from about 4 ms a frame at 64 to 0.5 ms. ``refit_max`` = ``refit_every`` keeps the fixed gap.
    """

    run_frames: int = 3
    refit_every: int = 64
    trusted_below: float = 0.15
    refit_max: int = 512

    def __post_init__(self) -> None:
        if int(self.run_frames) < 2:
            raise SveliveError(f"noise schedule: run_frames must be >= 2, got {self.run_frames}")
        if int(self.refit_every) != 0 and int(self.refit_every) < int(self.run_frames):
            raise SveliveError(f"noise schedule: refit_every must be 0 or >= run_frames, got {self.refit_every}")
        if int(self.refit_every) != 0 and int(self.refit_max) < int(self.refit_every):
            raise SveliveError(f"noise schedule: refit_max must be >= refit_every, got {self.refit_max}")
        if not self.trusted_below > 0:
            raise SveliveError(f"noise schedule: trusted_below must be > 0, got {self.trusted_below}")


class StreamNoise:
    """The noise model of one stream whose camera does not give its gain or read noise, refined as frames come.

    The first frame gives the single-frame estimate (:func:`estimate_from_frame`, what
    ``svelive.reconstruct`` uses); then runs of ``schedule.run_frames`` consecutive frames, with the
    pixels the motion tests found static, feed a :class:`NoiseTracker` (as the live service's noise
    stage does), fitted after the first run's second and last frames, then once per run, a run
    starting every ``schedule.refit_every`` frames. A run broken by a frame of unknown motion (a
    reset, a cut) is dropped; before the first complete run the next frame starts another. The first
    run's last fit replaces the fit after its second frame whatever it says (it holds that fit's samples
    and the three frames'); a later run's fit that disagrees with the model (:func:`agree`) keeps the
    model but distrusts it until a fit agrees. While the model is trusted and each later run's fit agrees with
    it, the gap between runs doubles up to ``schedule.refit_max`` (:meth:`_next_wait`); a fit that disagrees
    brings it back. A given gain or read noise is kept. One caller of
    :meth:`first` and :meth:`observe` at a time, frames in order; :attr:`estimate` and :attr:`trusted`
    may be read from any thread.

    With an ``executor`` (one thread: the live service, where a fit's 250 ms at 1920x1200 would stall the
    stream) the tracker reads a run's frames and fits there, in order, and a fit's model is taken when it
    is done; the gap to the next run is then chosen from the trust and agreement before that fit, and cut back
    to the schedule's ``refit_every`` when that fit disagrees. A failure there is
    kept in :attr:`error` (the model in use stays); without one it is raised to the caller.
    """

    def __init__(self, schedule: NoiseSchedule = NoiseSchedule(), tracker: NoiseTracker | None = None,
                 executor: Executor | None = None) -> None:
        self.schedule = schedule
        self.tracker = tracker if tracker is not None else NoiseTracker()
        self.executor = executor
        self.error: str | None = None  # the last failure of the executor's work, None after a success
        self._lock = threading.RLock()  # the model, for readers on other threads than the executor's
        # the tracker, used by one piece of work at a time: an executor's work still under way when the executor
        # was dropped (a closed stream then fits in line) is finished before in-line work starts
        self._work_lock = threading.Lock()
        self.fits = 0  # tracker fits so far
        self._estimate: NoiseEstimate | None = None
        self._fitted = False  # whether _estimate is a fit with temporal samples (not the first frame's)
        self._position: int | None = None  # the last frame fed's place in its run, None between runs
        self._runs = 0  # complete runs
        self._wait = 0  # frames before the next run starts
        self._untrusted_runs = 0  # complete runs in a row after which the model was not trusted
        self._conflict = False  # whether the tracker's last fit contradicted the model in use
        self._agreed = 0  # later runs' fits in a row that agreed with a trusted model (the back-off's doublings)
        self._disagreed = False  # a fit disagreed since the current gap was chosen (set with the model's lock)
        self._gap = 0  # frames of the current gap between runs, as chosen

    @property
    def estimate(self) -> NoiseEstimate | None:
        """The model in use, None before the first frame."""
        with self._lock:
            return self._estimate

    @property
    def trusted(self) -> bool:
        """Whether the model is known well enough for fusion (``schedule.trusted_below``): given, or a
        tracker's fit with temporal samples that states it that well. The first frame's estimate never is."""
        with self._lock:
            estimate, fitted, conflict = self._estimate, self._fitted, self._conflict
        if estimate is None:
            return False
        if estimate.source == "given":
            return True
        return fitted and not conflict and variance_uncertainty(estimate) <= self.schedule.trusted_below

    def first(self, raw: np.ndarray, camera: Camera, *, signal: np.ndarray | None = None) -> NoiseEstimate:
        """The model for a frame when there is none yet: the frame's own (:func:`estimate_from_frame`, as a
        single frame is reconstructed), kept until the tracker's first fit."""
        with self._lock:
            if self._estimate is None:
                self._estimate = estimate_from_frame(raw, camera, signal=signal)
            return self._estimate

    def needs_static(self) -> bool:
        """Whether :meth:`observe` reads the next frame's static mask (the frame continues a run; a frame
        that starts one or waits between runs gives no temporal samples), so a caller makes it only then."""
        return self._position is not None

    def observe(self, raw: np.ndarray, camera: Camera, static: np.ndarray | None, *,
                signal: np.ndarray | None = None) -> NoiseEstimate | None:
        """Feed the stream's next frame, on the schedule (the tracker reads only the frames of its runs).

        Args:
            raw: uint (H, W), the frame as delivered; camera: its camera (without an estimated model).
            static: bool (H, W), the pixels found static against the previous frame given here, or
                None where that is unknown (the first frame, after a reset or a lost frame).
            signal: the linear signal above black for a camera with a response curve.
        Returns:
            The new model when the tracker was fitted after this frame, else None (always None with an
            executor: the fit is taken when done).
        """
        schedule = self.schedule
        if self._position is not None and static is None:  # the run is broken: drop it
            self._position = None
        if self._position is None:
            if self._disagreed:  # a fit done on the executor during a backed-off gap: the schedule's gap at most
                with self._lock:
                    self._disagreed = False
                elapsed = self._gap - self._wait
                self._wait = min(self._wait, max(schedule.refit_every - schedule.run_frames, 0) - elapsed)
            if self._runs > 0 and (self._wait > 0 or schedule.refit_every <= 0):
                self._wait -= 1
                return None
            self._position = 0
            static = None
        else:
            self._position += 1
        last = self._position == schedule.run_frames - 1
        if last:
            self._position = None
            self._runs += 1
        fit = last or (self._runs == 0 and self._position >= 1)
        work = partial(self._work, raw, camera, static, signal, fit, self._runs, last)
        if self.executor is not None:
            if last:
                self._wait = self._next_wait()
            self.executor.submit(work)
            return None
        taken = work()
        if last:
            self._wait = self._next_wait()
        return taken

    def _work(self, raw: np.ndarray, camera: Camera, static: np.ndarray | None, signal: np.ndarray | None,
              fit: bool, runs: int, last: bool = False) -> NoiseEstimate | None:
        """The tracker's part of :meth:`observe`: read the frame, and fit and take the model if ``fit``;
        ``runs``: the complete runs when the frame came; ``last``: the frame ends its run (the tracker then
        keeps no frame until the next run, :meth:`NoiseTracker.rest`: 20 MiB at 1920x1200)."""
        try:
            with self._work_lock:
                self.tracker.add(raw, camera, static, signal=signal)
                if last:
                    self.tracker.rest()
                if not fit:
                    return None
                model = self.tracker.fit()
        except Exception as exc:
            if self.executor is None:
                raise
            self.error = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            return None
        self.error = None
        with self._lock:
            self.fits += 1
            return self._take(model, runs)

    def _next_wait(self) -> int:
        """Frames between the run just complete and the next: the schedule's once the model is trusted, doubled
        for each later run's fit in a row that agreed with the trusted model, up to ``refit_max`` (run start to
        run start: 64, 128, 256, 512, 512, ...); while it is not trusted (the stream's output is then its single
        frames), 0, 3, 9, 21, 45, ... frames (the gaps doubling up to the schedule's), so that a model the first
        run could not state well enough (a small or busy frame) is refined within a few runs at a bounded cost:
        about log2(refit_every / run_frames) runs more."""
        schedule = self.schedule
        full = max(schedule.refit_every - schedule.run_frames, 0)
        if self.trusted:
            self._untrusted_runs = 0
            with self._lock:
                doublings = min(self._agreed, 32)
            interval = min(schedule.refit_max, schedule.refit_every * 2 ** doublings)
            self._gap = max(interval - schedule.run_frames, 0) if schedule.refit_every > 0 else full
        else:
            self._untrusted_runs += 1
            self._gap = min(full, schedule.run_frames * (2 ** (self._untrusted_runs - 1) - 1))
        return self._gap

    def _take(self, fit: NoiseEstimate, runs: int) -> NoiseEstimate | None:
        """The model after a tracker's fit (see the class): the fit, or None where the model in use is kept."""
        if fit.source == "default":  # the frames told nothing (no unclipped flat or static pixels): keep the model
            return None
        if self._fitted and runs > 1 and not agree(fit, self._estimate):
            # two fits of one sensor that their stated uncertainties cannot reconcile: something the motion
            # masks missed (or texture) is in the samples; keep the model in use, and distrust it until a fit agrees.
            # Not within the first run: its last fit holds every sample of the one before and the three frames'
            # (unbiased) samples, where the fit after two frames has only a pair's, which can be confidently
            # wrong (BrightRings 3 000 e- / 2 e-, 4 stops under: gain 2.2x stated 14 %, then 1.0x from three)
            self._conflict, self._agreed, self._disagreed = True, 0, True
            return None
        later = self._fitted and runs > 1
        self._agreed = self._agreed + 1 if later and self.trusted else 0
        self._estimate, self._fitted, self._conflict = fit, True, False
        if not self.trusted:
            self._agreed, self._disagreed = 0, True
        return self._estimate
