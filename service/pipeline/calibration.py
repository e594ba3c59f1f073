"""Calibration in the live pipeline: the response in use (configured or calibrated live) and the mask's pixel map."""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import numpy as np

from svelive.calibrate import Response, calibrate_frame, load_mask, load_response
from svelive.camera import Camera
from svelive.errors import SveliveError
from svelive.frame import Frame


class CalibrationBusy(SveliveError):
    """A calibration was asked while another one runs."""


class Calibration:
    """The response every frame is linearised through, and the per-pixel exposure map of the mask.

    The configured response and mask files are read at construction, so a bad
    file fails before serving. ``newest_raw`` gives the newest captured raw
    frame (or None), which ``calibrate_response`` fits. :meth:`apply` makes the
    camera every frame is reconstructed with.
    """

    def __init__(self, response_path: str | None, mask_path: str | None,
                 newest_raw: Callable[[], Frame | None]) -> None:
        self._newest_raw = newest_raw
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
            data = calibrate_frame(frame.raw, frame.camera.require_pattern(), frame.sensor, max_degree=max_degree)
        finally:
            self.busy.release()
        data.update(frame_id=frame.frame_id, applied=bool(apply))
        self._calibration = data
        if apply:
            with self._lock:
                self._response, self._origin = Response.from_dict(data), "calibrated live"
        return data

    def last_calibration(self) -> dict[str, Any] | None:
        """The result of the last successful calibrate_response, or None."""
        return self._calibration

    def reset_response(self) -> dict[str, Any] | None:
        """Go back to the configured response (the ``response`` file, or none); returns response_state()."""
        with self._lock:
            self._response, self._origin = self._configured_response, self._response_path
        return self.response_state()

    def response_state(self) -> dict[str, Any] | None:
        """The response in use: origin (file path or "calibrated live"), degree, coefficients, domain; None if linear."""
        with self._lock:
            response, origin = self._response, self._origin
        if response is None:
            return None
        return {"origin": origin, "degree": response.degree, "coefficients": list(response.coefficients),
                "domain": list(response.domain)}
