"""A live exposure sweep whose source is reopened half-way (the camera lost and found again) fails with
a one-line error instead of fitting frames taken at the reopened camera's own exposure time as if they
were the sweep's (service/pipeline/calibration.py, exposed_as_set)."""

from __future__ import annotations

import time

import httpx
import numpy as np

from tests.test_calibration_sweep import URL, ExposureSource, server, wait_job
from tests.test_service_helpers import Camera


def test_a_sweep_whose_source_is_reopened_fails_and_applies_nothing(monkeypatch):
    camera = Camera(fps=25.0, raws=[np.zeros((192, 224), np.uint16)])
    sources: list[ExposureSource] = []

    def factory() -> ExposureSource:
        sources.append(ExposureSource(camera))
        return sources[-1]

    with server(monkeypatch, factory) as srv:
        srv.wait_for(lambda s: s["frames"]["captured"] > 2)
        camera.paused = True  # the sweep waits at its first step
        r = httpx.post(srv.url + URL, json={"sweep": [10_000, 15_000], "apply": True}, timeout=10)
        assert r.status_code == 202, r.text
        job = r.json()
        first = sources[-1]
        camera.plugged = False  # lost: the capture stage reopens the source once it is back
        srv.wait_for(lambda s: s["source"]["state"] == "offline")
        camera.plugged = True
        camera.paused = False
        deadline = time.monotonic() + 20
        while len(sources) < 2 or sources[-1].exposure_of == {}:  # the reopened source delivers
            assert time.monotonic() < deadline, "the source was not reopened"
            time.sleep(0.02)
        done, _ = wait_job(srv, job["id"])
        assert done["state"] == "failed", done
        assert "reopened during the sweep" in done["error"] and "\n" not in done["error"]
        assert "exposed at 10000, not at the 15000" in done["error"]
        assert first.changes[:2] == [10_000.0, 15_000.0]  # the sweep set its times on the source it began with
        state = srv.state()
        assert state["response"] is None  # nothing applied
        kept = httpx.get(srv.url + URL, timeout=10).json()
        assert set(kept) == {"job"} and kept["job"]["state"] == "failed"  # no calibration kept, only the job
