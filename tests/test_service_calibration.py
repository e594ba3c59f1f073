"""Calibration in the live service (issue 7): POST /api/calibrate/response on the newest frame, applying a
response live, and serving with --response / --mask files. Against a real uvicorn server, as the other tests."""

from __future__ import annotations

import subprocess
import sys
import time

import httpx
import numpy as np
import pytest

from service.pipeline import Pipeline, PipelineConfig
from service.settings import resolve
from svelive.calibrate import CURVES, Response, linearise, load_mask, load_response, save_response
from svelive.core.errors import SveliveError
from svelive.core.pattern import Pattern
from svelive.exr import read_exr
from tests.test_service_helpers import PATTERN, SENSOR, Camera, ServerThread, chart_raws, make_camera, reference_image


def snapshot_after(srv: ServerThread, frame_id: int) -> tuple[np.ndarray, int]:
    """(Y, frame id) of the first EXR snapshot of a frame newer than ``frame_id``."""
    deadline = time.monotonic() + 10
    while True:
        channels, header = read_exr(httpx.get(srv.url + "/snapshot.exr", timeout=10).content)
        if int(header["frameId"]) > frame_id:
            return channels["Y"], int(header["frameId"])
        assert time.monotonic() < deadline, "no newer frame"
        time.sleep(0.05)


def test_calibrate_endpoint_fits_the_newest_frame_applies_it_live_and_refuses_bad_frames():
    camera = Camera(fps=15.0, raws=chart_raws("gamma2.2"), paused=True)
    url = "/api/calibrate/response"
    with ServerThread(camera) as srv:
        assert httpx.post(srv.url + url, timeout=10).status_code == 503  # no frame yet
        assert httpx.get(srv.url + url, timeout=10).status_code == 404
        camera.paused = False
        srv.wait_for(lambda s: s["frames"]["reconstructed"] > 1)

        r = httpx.post(srv.url + url, timeout=60)  # no body: defaults
        assert r.status_code == 200, r.text
        data = r.json()
        assert data["applied"] is False and srv.state()["response"] is None
        lo, hi = data["stats"]["measured_range"]
        assert hi - lo > 0.9
        m = np.asarray(data["curve"]["brightness"])
        assert m.size == 65 and m[0] == 0 and m[-1] == 1
        inside = (m >= lo) & (m <= hi)
        error = np.abs(np.asarray(data["curve"]["linear"]) - CURVES["gamma2.2"].inverse(m))[inside]
        assert error.max() < 0.02, error.max()
        assert data["frame_id"] in camera.delivered
        assert httpx.get(srv.url + url, timeout=10).json() == data

        # bad requests: 422 with the field named, nothing applied
        for body, word in (({"max_degree": 0}, "max_degree"), ({"apply": "maybe"}, "apply"), ({"x": 1}, "x")):
            r = httpx.post(srv.url + url, json=body, timeout=10)
            assert r.status_code == 422 and word in r.text, (body, r.text)
        assert srv.state()["response"] is None

        # applied live: the frames after it are linearised through the new response, exactly
        r = httpx.post(srv.url + url, json={"apply": True, "max_degree": 4}, timeout=60)
        assert r.status_code == 200 and r.json()["applied"] is True
        applied = r.json()
        state = srv.state()
        assert state["response"]["origin"] == "calibrated live"
        assert state["response"]["coefficients"] == applied["coefficients"]
        image, frame_id = snapshot_after(srv, state["frames"]["last_frame_id"] + 1)
        response = Response.from_dict(applied)
        expected = reference_image(camera.delivered[frame_id], response=response)
        np.testing.assert_array_equal(image, expected)
        unlinearised = reference_image(camera.delivered[frame_id])
        assert not np.array_equal(image, unlinearised)

        # a frame that cannot calibrate (flat grey: no brightness span) is a 422 with the reason,
        # and the response in use stays
        camera.raws[:] = [np.full((192, 224), 900, np.uint16)] * 2
        last = srv.state()["frames"]["last_frame_id"]
        srv.wait_for(lambda s: s["frames"]["last_frame_id"] > last + 2)
        r = httpx.post(srv.url + url, json={"apply": True}, timeout=60)
        assert r.status_code == 422, r.text
        assert isinstance(r.json()["detail"], str) and len(r.json()["detail"]) > 20
        assert srv.state()["response"]["coefficients"] == applied["coefficients"]

        # one calibration at a time
        assert srv.pipeline.calibration.busy.acquire(timeout=5)
        try:
            assert httpx.post(srv.url + url, timeout=10).status_code == 409
        finally:
            srv.pipeline.calibration.busy.release()

        r = httpx.delete(srv.url + url, timeout=10)
        assert r.status_code == 200 and r.json() == {"response": None}
        assert srv.state()["response"] is None


def test_token_guards_calibration():
    camera = make_camera(fps=10.0, n=2)
    with ServerThread(camera, token="tok") as srv:
        for method in ("POST", "GET", "DELETE"):
            r = httpx.request(method, srv.url + "/api/calibrate/response", timeout=10)
            assert r.status_code == 401 and r.content == b"unauthorized\n"


def write_files(tmp_path, shape=(192, 224)) -> tuple[str, str]:
    """A response file (I = M^2 over the sensor's range) and a mask file (nominal tile, +-5 % per pixel)."""
    response = Response((0.0, 0.0, 1.0), (0.0, 1.0), SENSOR.black_level, SENSOR.white_level)
    response_path = save_response(response, tmp_path / "response.json")
    rng = np.random.default_rng(3)
    pixel_map = Pattern.parse(PATTERN).exposure_map(shape) * rng.uniform(0.95, 1.05, shape).astype(np.float32)
    mask_path = tmp_path / "mask.npz"
    np.savez(mask_path, pixel_map=pixel_map)
    return str(response_path), str(mask_path)


def test_serve_with_response_and_mask_files_reconstructs_through_them(tmp_path):
    response_path, mask_path = write_files(tmp_path)
    camera = make_camera(fps=15.0, n=3)
    with ServerThread(camera, response=response_path, mask=mask_path) as srv:
        state = srv.wait_for(lambda s: s["frames"]["reconstructed"] > 1)
        assert state["response"]["origin"] == response_path and state["response"]["degree"] == 2
        assert state["mask"] == mask_path and state["reconstruct_error"] is None
        image, frame_id = snapshot_after(srv, -1)
        pattern = Pattern.parse(PATTERN).with_pixel_map(load_mask(mask_path))
        raw = camera.delivered[frame_id]
        expected = reference_image(raw, pattern, load_response(response_path))
        np.testing.assert_array_equal(image, expected)
        # and it differs from the nominal, unlinearised reconstruction
        plain = reference_image(raw)
        assert not np.array_equal(image, plain)
        np.testing.assert_array_equal(expected, reference_image(linearise(raw, load_response(response_path), SENSOR),
                                                                pattern))
        # DELETE goes back to the configured file, not to linear
        assert httpx.delete(srv.url + "/api/calibrate/response", timeout=10).json()["response"]["origin"] \
            == response_path


def test_a_mask_of_the_wrong_size_is_reported_in_the_state(tmp_path):
    _, mask_path = write_files(tmp_path, shape=(96, 224))
    with ServerThread(make_camera(fps=15.0, n=2), mask=mask_path) as srv:
        state = srv.wait_for(lambda s: s["reconstruct_error"] is not None)
        assert "224x96" in state["reconstruct_error"] and "224x192" in state["reconstruct_error"]
        assert state["frames"]["reconstructed"] == 0 and state["drops"]["reconstruct_error"] > 0


def test_response_and_mask_settings_precedence_and_bad_files(tmp_path):
    response_path, mask_path = write_files(tmp_path)
    config = tmp_path / "svelive.toml"
    config.write_text(f'[serve]\nresponse = "{tmp_path / "file.json"}"\nmask = "{mask_path}"\nworkers = 1\n')
    settings = resolve({"response": None}, {"SVELIVE_CONFIG": str(config), "SVELIVE_RESPONSE": response_path})
    assert settings.pipeline.response == response_path and settings.pipeline.mask == mask_path
    assert settings.pipeline.workers == 1
    assert resolve({"response": "cli.json"}, {"SVELIVE_RESPONSE": response_path}).pipeline.response == "cli.json"
    with pytest.raises(SveliveError, match="workers"):
        resolve({"workers": -1}, {})
    with pytest.raises(SveliveError, match="missing.json"):
        Pipeline(PipelineConfig(response=str(tmp_path / "missing.json")))
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(SveliveError, match="bad.npz"):
        Pipeline(PipelineConfig(mask=str(tmp_path / "bad.npz")))
    proc = subprocess.run([sys.executable, "-m", "svelive.cli", "serve", "--response", str(tmp_path / "nope.json")],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "nope.json" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
