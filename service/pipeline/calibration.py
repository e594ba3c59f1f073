"""Calibration in the live pipeline: the response in use (configured or calibrated live), the
exposure sweep that calibrates it from several frames, and the mask's pixel map."""

from __future__ import annotations

import copy
import math
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from svelive.calibrate import Response, load_mask, load_response
from svelive.calibrate.response import SWEEP_KNOTS, calibrate_frame
from svelive.capture import AfterChange, Source
from svelive.core.camera import Camera, one_colour_plane
from svelive.core.errors import SveliveError
from svelive.core.frame import Frame
from svelive.memory import release_memory

#: most exposure times one sweep takes
MAX_SWEEP = 16

#: the sweep's refusal once the source has ended (an ``images:`` folder played out, a replay's end)
ENDED = ("the source has ended, so no exposure time can be stepped and it cannot sweep; calibrate from its "
         "last frame (POST without \"sweep\") or sweep offline (svelive calibrate response FRAMES "
         "--exposure-times)")

#: relative difference between a frame's exposure time and the one the sweep set beyond which they differ
EXPOSURE_RTOL = 1e-3


def exposed_as_set(frame: Frame, applied: float, step: int) -> None:
    """A one-line SveliveError when ``frame`` says it was exposed at another time than the sweep's step
    ``step`` (0-based) set: the source was reopened meanwhile (a camera or replay reopened after a failure
    starts at its own exposure time, and the sweep set the time on the source it started with). A frame
    that does not say its exposure time passes."""
    taken = frame.exposure_time
    if taken is not None and not math.isclose(taken, applied, rel_tol=EXPOSURE_RTOL):
        raise SveliveError(f"the frame of step {step + 1} was exposed at {taken:g}, not at the {applied:g} the "
                           "sweep set: the source was reopened during the sweep; start it again")


class CalibrationBusy(SveliveError):
    """A calibration was asked while another one runs."""


class ExposureUnsupported(SveliveError):
    """The source cannot set its exposure time (a sweep is impossible)."""


def check_sweep(times: list[float]) -> list[float]:
    """The sweep's exposure times as floats; a one-line SveliveError when they are not 1..16 positive numbers."""
    if not 1 <= len(times) <= MAX_SWEEP:
        raise SveliveError(f"sweep: give 1 to {MAX_SWEEP} exposure times, got {len(times)}")
    values = [float(t) for t in times]
    if not all(math.isfinite(t) and t > 0 for t in values):
        raise SveliveError(f"sweep: exposure times must be positive numbers, got {times}")
    if len(set(values)) < len(values):
        raise SveliveError(f"sweep: exposure times must differ, got {times}")
    return values


class Calibration:
    """The response every frame is linearised through, and the per-pixel exposure map of the mask.

    The configured response and mask files are read at construction, so a bad
    file fails before serving. ``newest_raw`` gives the newest captured raw
    frame (or None), which ``calibrate_response`` fits. :meth:`apply` makes the
    camera every frame is reconstructed with.
    """

    def __init__(self, response_path: str | None, mask_path: str | None,
                 newest_raw: Callable[[], Frame | None], stop: threading.Event | None = None) -> None:
        self._newest_raw = newest_raw
        self._stop = stop if stop is not None else threading.Event()
        self._response_path = response_path
        self._configured_response = load_response(response_path) if response_path else None
        self._response = self._configured_response
        self._origin = response_path
        self._lock = threading.Lock()  # guards the response and its origin
        #: held while a calibration runs (one at a time)
        self.busy = threading.Lock()
        self.pixel_map: np.ndarray | None = load_mask(mask_path) if mask_path else None
        self._calibration: dict[str, Any] | None = None
        self._applied: tuple[tuple[Camera, Response | None], Camera] | None = None
        self._job: dict[str, Any] | None = None  # the newest sweep: progress, then result or error
        self._jobs = 0

    def apply(self, camera: Camera) -> Camera:
        """The camera with the response in use and the mask's per-pixel exposure map.

        Returns the same object while neither the camera nor the response changes,
        so a reconstructor built for it can be kept (a per-pixel map compares by identity).
        """
        key = (camera, self._response)
        if self._applied is not None and self._applied[0] == key:
            return self._applied[1]
        pattern = camera.require_pattern()
        if self.pixel_map is not None:
            pattern = pattern.with_pixel_map(self.pixel_map)
        applied = camera.replace(pattern=pattern, response=key[1])
        self._applied = (key, applied)
        return applied

    @property
    def response(self) -> Response | None:
        """The response in use; None: the camera is linear."""
        return self._response

    def calibrate_response(self, max_degree: int = 6, apply: bool = False) -> dict[str, Any] | None:
        """Fit the camera's response to the newest raw frame (``svelive.calibrate.calibrate_frame``).

        Runs on the caller's thread (seconds at full HD: call it off the event loop).
        With ``apply`` the response linearises every frame from the next one on (in
        memory: a restart goes back to the configured ``response``). Returns the
        response JSON with ``curve``, ``frame_id`` and ``applied``; None when no
        frame has arrived yet. Raises SveliveError when the frame cannot calibrate
        (the response in use is kept) and CalibrationBusy while another runs.
        """
        if not 1 <= max_degree <= 10:
            raise SveliveError(f"max_degree must be 1..10, got {max_degree}")
        frame = self._newest_raw()
        if frame is None:
            return None
        if not self.busy.acquire(blocking=False):
            raise CalibrationBusy("a response calibration is already running")
        try:
            raw, pattern = one_colour_plane(frame.raw, frame.camera)  # a colour camera: one filter's pixels
            data = calibrate_frame(raw, pattern, frame.sensor, max_degree=max_degree)
            del raw
            data["frame_id"] = frame.frame_id
        finally:
            self.busy.release()
            del frame
            release_memory()
        return self._keep(data, apply)

    def _keep(self, data: dict[str, Any], apply: bool) -> dict[str, Any]:
        """Record a successful fit as the last calibration; with ``apply`` make it the response in use."""
        data["applied"] = bool(apply)
        with self._lock:
            self._calibration = data
            if apply:
                self._response, self._origin = Response.from_dict(data), "calibrated live"
        return copy.deepcopy(data)

    # ----- the exposure sweep (a background job) ----------------------------
    def start_sweep(self, times: list[float], source: Source | None, max_degree: int = 6, apply: bool = False,
                    settle_frames: int = 1, frame_timeout_s: float = 5.0, max_knots: int = SWEEP_KNOTS) -> dict[str, Any]:
        """Start stepping ``source``'s exposure time through ``times`` in a background thread.

        At each step the exposure is set, the frame that arrives ``settle_frames`` frames after
        the first one captured after the change is kept (the one in flight may have been exposed
        before it), and once every step has its frame the response is fitted to them all with the
        exposure times the camera reported back (``svelive.calibrate.fit_response``), the camera
        going back to its exposure time meanwhile. :meth:`job_state` reports the progress and
        the result; returns it. Raises ExposureUnsupported when the source cannot set its
        exposure time (also once it has ended, or for times it cannot take: checked here, before
        the job starts), CalibrationBusy while another calibration runs, SveliveError for bad
        times or when no frame came yet.
        """
        if not 1 <= max_degree <= 10:
            raise SveliveError(f"max_degree must be 1..10, got {max_degree}")
        if not 0 <= max_knots <= 16:
            raise SveliveError(f"max_knots must be 0..16 (0: polynomials only), got {max_knots}")
        times = check_sweep(times)
        if source is None and self._newest_raw() is not None:
            raise ExposureUnsupported(ENDED)
        if source is None or self._newest_raw() is None:
            raise SveliveError("no frame yet: the sweep needs a connected camera")
        original = source.exposure_time()
        if original is None:
            raise ExposureUnsupported(f"source {source.spec} cannot set its exposure time, so it cannot sweep; "
                                      "calibrate from one frame (POST without \"sweep\") or sweep offline "
                                      "(svelive calibrate response FRAMES --exposure-times)")
        try:
            source.check_exposure_times(times)
        except SveliveError as exc:
            raise ExposureUnsupported(str(exc)) from None
        if not self.busy.acquire(blocking=False):
            raise CalibrationBusy("a response calibration is already running")
        with self._lock:
            self._jobs += 1
            self._job = {"id": self._jobs, "state": "running", "stage": "starting", "step": 0, "steps": len(times),
                         "sweep": times, "exposure_time_before": original, "exposure_times": [], "frame_ids": [],
                         "restored": None, "error": None, "apply": bool(apply), "max_knots": max_knots,
                         "started_s": time.time(),
                         "finished_s": None}
            job = copy.deepcopy(self._job)
        thread = threading.Thread(target=self._run_sweep, name="svelive-sweep", daemon=True,
                                  args=(times, source, original, max_degree, max_knots, apply, settle_frames,
                                        frame_timeout_s))
        thread.start()
        return job

    def _update(self, **changes: Any) -> None:
        with self._lock:
            if self._job is not None:
                self._job.update(changes)

    def _run_sweep(self, times: list[float], source: Source, original: float, max_degree: int, max_knots: int,
                   apply: bool, settle_frames: int, frame_timeout_s: float) -> None:
        frames: list[Frame] = []
        planes: list[tuple[np.ndarray, Any]] = []
        applied: list[float] = []
        error: str | None = None
        try:
            for i, t in enumerate(times):
                self._update(stage=f"exposure {i + 1}/{len(times)}: {t:g}", step=i)
                applied.append(source.set_exposure_time(t))
                frames.append(self._frame_after(time.monotonic_ns(), settle_frames, frame_timeout_s))
                exposed_as_set(frames[-1], applied[-1], i)
                self._update(exposure_times=list(applied), frame_ids=[f.frame_id for f in frames], step=i + 1)
            self._restore(source, original)
            shapes = {f.raw.shape for f in frames}
            if len(shapes) > 1:
                raise SveliveError(f"the frames of the sweep differ in size ({sorted(shapes)}): the camera's "
                                   "region changed during the sweep; try again")
            self._update(stage="fitting")
            planes = [one_colour_plane(f.raw, f.camera) for f in frames]  # a colour camera: one filter's pixels
            data = calibrate_frame([raw for raw, _ in planes], planes[0][1], frames[0].sensor,
                                   max_degree=max_degree, max_knots=max_knots, exposure_times=applied,
                                   progress=lambda text: self._update(stage=f"fitting: {text}"))
            data.update(frame_id=frames[-1].frame_id, frame_ids=[f.frame_id for f in frames])
            self._keep(data, apply)
            del data
        except Exception as exc:  # reported in the job; the response in use stays
            error = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        finally:
            if self._job is not None and self._job["restored"] is None:
                try:
                    self._restore(source, original)
                except Exception as exc:  # noqa: BLE001 - a camera gone meanwhile
                    error = f"{error + '; ' if error else ''}exposure time not restored: {exc}"
            del frames, planes
            self.busy.release()
            release_memory()
            # last, so that a client seeing the job end can start the next one
            self._update(state="failed" if error else "done", stage="failed" if error else "done", error=error,
                         finished_s=time.time())

    def _restore(self, source: Source, original: float) -> None:
        self._update(stage="restoring the exposure time")
        self._update(restored=source.set_exposure_time(original))

    def _frame_after(self, changed_ns: int, settle_frames: int, timeout_s: float) -> Frame:
        """The ``settle_frames``-th frame after the first one captured after ``changed_ns`` (monotonic ns)."""
        deadline = time.monotonic() + timeout_s
        settled = AfterChange(changed_ns, settle_frames)
        while not self._stop.is_set() and time.monotonic() < deadline:
            frame = self._newest_raw()
            if frame is not None and settled.shows(frame):
                return frame
            self._stop.wait(0.005)
        if self._stop.is_set():
            raise SveliveError("the service is stopping")
        raise SveliveError(f"no frame within {timeout_s:g} s of changing the exposure time")

    def job_state(self) -> dict[str, Any] | None:
        """The newest sweep: id, state ("running", "done", "failed"), stage, step/steps, sweep,
        exposure_times (as the camera applied them), frame_ids, exposure_time_before, restored,
        error, apply, max_knots; None before the first."""
        with self._lock:
            return copy.deepcopy(self._job)

    def last_calibration(self) -> dict[str, Any] | None:
        """The result of the last successful calibration (one frame or a sweep), or None; with
        ``job`` (:meth:`job_state`) once a sweep was started. ``applied`` is true while that
        result is the response in use."""
        with self._lock:
            data = None if self._calibration is None else dict(self._calibration)
            job = copy.deepcopy(self._job)
        if job is not None:
            data = {**(data or {}), "job": job}
        return data

    def reset_response(self) -> dict[str, Any] | None:
        """Go back to the configured response (the ``response`` file, or none); returns response_state().
        The last calibration stays readable, no longer ``applied``."""
        with self._lock:
            self._response, self._origin = self._configured_response, self._response_path
            if self._calibration is not None:
                self._calibration = {**self._calibration, "applied": False}
        return self.response_state()

    def response_state(self) -> dict[str, Any] | None:
        """The response in use: origin (file path or "calibrated live"), degree, coefficients, domain; None if linear."""
        with self._lock:
            response, origin = self._response, self._origin
        if response is None:
            return None
        return {"origin": origin, "degree": response.degree, "coefficients": list(response.coefficients),
                "domain": list(response.domain)}
