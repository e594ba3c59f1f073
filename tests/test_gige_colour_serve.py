"""End to end in colour: the fake GigE camera in a Bayer format through a real ``svelive serve`` process.

The camera (arv-fake-gv-camera-0.8) and the service run as subprocesses on
127.0.0.1 and are stopped by their pids; every wait is bounded. Where Aravis or
the fake camera is missing these tests skip, except under CI=true (as in
tests/test_capture_gige.py).
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from typing import Any

import cv2
import httpx
import numpy as np
import pytest

from svelive.exr import read_exr
from tests.test_capture_gige import _MISSING, ADDRESS, FakeCamera
from tests.test_service_helpers import free_port, mjpeg_parts, stop_process

if _MISSING and os.environ.get("CI") != "true":
    pytestmark = pytest.mark.skip(reason=_MISSING)

WIDTH, HEIGHT = 320, 240


class Service:
    """One ``svelive serve`` process on a free loopback port, stopped by its pid."""

    def __init__(self, *args: str) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        cmd = [sys.executable, "-m", "svelive.cli", "serve", "--port", str(self.port), "--log-level", "warning",
               *args]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)

    def wait_for(self, predicate: Callable[[dict[str, Any]], bool], timeout: float,
                 failed: Callable[[dict[str, Any]], str | None] = lambda s: None) -> dict[str, Any]:
        """The first /api/state that satisfies ``predicate`` within ``timeout`` seconds; an
        AssertionError at once when ``failed`` returns a reason."""
        deadline = time.monotonic() + timeout
        state: dict[str, Any] = {}
        while time.monotonic() < deadline:
            assert self.proc.poll() is None, f"svelive serve exited: {self.proc.stderr.read()}"  # type: ignore[union-attr]
            try:
                state = httpx.get(self.url + "/api/state", timeout=5).json()
            except httpx.HTTPError:
                state = {}  # not listening yet
            if state and predicate(state):
                return state
            reason = failed(state) if state else None
            assert reason is None, reason
            time.sleep(0.25)
        raise AssertionError(f"no state satisfied the condition within {timeout} s; last: {state}")

    def stop(self) -> None:
        stop_process(self.proc)


def reconstruction_fails(state: dict[str, Any]) -> str | None:
    """Why no frame gets reconstructed, once thirty were captured and none was."""
    if state["frames"]["captured"] > 30 and state["frames"]["reconstructed"] == 0 and state["reconstruct_error"]:
        return f"every frame fails to reconstruct: {state['reconstruct_error']}"
    return None


@pytest.fixture(scope="module")
def camera() -> Iterator[FakeCamera]:
    with FakeCamera("SVESERVE") as cam:
        yield cam


@pytest.fixture(scope="module")
def service(camera: FakeCamera) -> Iterator[Service]:
    srv = Service("--source", f"gige:{ADDRESS}", "--pattern", "1/1/8/8",
                  "--source-option", "pixel_format=BayerRG8", "--source-option", f"width={WIDTH}",
                  "--source-option", f"height={HEIGHT}", "--source-option", "fps=15")
    try:
        # the first start compiles the kernels (a minute at most on a loaded machine); then frames flow
        srv.wait_for(lambda s: s["frames"]["reconstructed"] >= 3, timeout=120, failed=reconstruction_fails)
        yield srv
    finally:
        srv.stop()


def test_monochrome_reading_of_the_bayer_camera_is_refused(camera: FakeCamera) -> None:
    """--cfa none for a Bayer camera: the source never opens; the state says why and names the fix.
    (First in this file: the colour service below then holds the camera's control channel.)"""
    srv = Service("--source", f"gige:{ADDRESS}", "--cfa", "none", "--source-option", "pixel_format=BayerRG8",
                  "--source-option", "width=64", "--source-option", "height=48")
    try:
        state = srv.wait_for(lambda s: "monochrome" in (s["source"]["error"] or ""), timeout=120)
    finally:
        srv.stop()
    error = state["source"]["error"]
    assert "BayerRG8, a Bayer format" in error and "drop --cfa none" in error and "\n" not in error
    assert state["frames"]["reconstructed"] == 0 and not state["source"]["online"]


def test_state_reports_the_colour_filter_of_the_bayer_camera(service: Service) -> None:
    state = service.wait_for(lambda s: s["source"]["online"], timeout=10)
    assert state["cfa"] == "RGGB" and state["pattern"] == "1/1/8/8"
    assert state["source"]["pixel_format"] == "BayerRG8" and state["reconstruct_error"] is None


def test_exr_snapshot_has_rgb_channels(service: Service) -> None:
    r = httpx.get(service.url + "/snapshot.exr", timeout=20)
    assert r.status_code == 200 and r.headers["content-type"] == "image/x-exr"
    channels, header = read_exr(r.content)
    assert {"R", "G", "B"} <= set(channels)
    rgb = np.dstack([channels[c] for c in "RGB"])
    assert rgb.shape == (HEIGHT, WIDTH, 3) and np.all(np.isfinite(rgb))
    # colour, not one channel three times: the fake camera's red and blue sites differ from its greens
    assert np.abs(rgb[..., 0] - rgb[..., 1]).mean() > 0.05 * rgb[..., 1].mean()
    assert np.abs(rgb[..., 2] - rgb[..., 1]).mean() > 0.05 * rgb[..., 1].mean()


def test_mjpeg_part_is_a_colour_image(service: Service) -> None:
    with httpx.stream("GET", service.url + "/stream.mjpg", timeout=20) as r:
        assert r.status_code == 200
        for headers, body in mjpeg_parts(r):
            if headers.get("x-signal") == "live":
                break
    image = cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_UNCHANGED)
    assert image is not None and image.shape == (HEIGHT, WIDTH, 3)
    b, g, r_ = (image[..., i].astype(np.float64) for i in range(3))
    # a grey preview has equal channels (up to JPEG's chroma rounding of a level or two)
    assert np.abs(r_ - g).mean() > 4 and np.abs(b - g).mean() > 4
