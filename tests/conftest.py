"""Shared fixtures: simulated frames of the shipped real HDR crops."""

from __future__ import annotations

try:
    # Before anything loads OpenCV and GStreamer: importing matplotlib's font code after both are
    # loaded aborts the process (measured: `import cv2`, `Gst.init`, then `import matplotlib.font_manager`).
    # No svelive command uses all three (bench: OpenCV + matplotlib; serve --rtsp: OpenCV + GStreamer);
    # the test process does.
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot  # noqa: F401
except ImportError:  # the bench extra is not installed: its tests skip
    pass

from pathlib import Path

import numpy as np
import pytest

from svelive import Pattern, Sensor, simulate
from svelive.simulation import exposure_scale, load_sample_scene


@pytest.fixture(scope="session")
def sensor12() -> Sensor:
    return Sensor.from_full_well(12, 10_000, 3)


@pytest.fixture(scope="session")
def scenes() -> dict[str, np.ndarray]:
    return {name: np.maximum(load_sample_scene(name), 0) for name in ("desk", "mttamwest", "cannon")}


def simulated(scene: np.ndarray, pattern: str, sensor: Sensor, stops_below_fill: float = 0.0, seed: int = 1):
    radiance = scene * exposure_scale(scene, Pattern.parse(pattern), sensor, stops_below_fill=stops_below_fill)
    return simulate(radiance, pattern, sensor, seed=seed)


#: Test files that need the machine to themselves: a fake GigE camera streaming over loopback (packets lost
#: when the CPU is short), RTSP clients, live frame rates and latencies, a browser with timeouts.
#: scripts/test.sh runs them after the others, which run on two workers.
SERIAL_FILES = frozenset({
    "test_calibration_sweep.py", "test_capture_gige.py", "test_colour_capture.py", "test_gige_colour_serve.py",
    "test_issue28_connections.py", "test_issue28_rtsp.py", "test_issue28_startup.py", "test_service_deploy.py",
    "test_service_rtsp.py", "test_live_quality.py", "test_service_realtime.py", "test_service_http.py",
    "test_service_warm_up.py", "test_viewer.py", "test_monitor.py",
})


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if Path(str(item.fspath)).name in SERIAL_FILES:
            item.add_marker(pytest.mark.serial)
