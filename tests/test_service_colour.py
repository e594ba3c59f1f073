"""The service with a colour (Bayer) SVE camera: colour MJPEG and JPEG, RGB EXR, white balance settings and refusals.

A real uvicorn server on a loopback port, fed by simulated RGGB frames of a shipped RGB scene seen under a
warm light (so that the automatic white balance has a cast to remove).
"""

from __future__ import annotations

import dataclasses
import threading
import time

import cv2
import httpx
import numpy as np
import pytest
import uvicorn

from service.app import create_app, listen_socket
from service.pipeline import Pipeline, PipelineConfig
from service.settings import ServerSettings
from svelive import Reconstructor
from svelive.core.camera import Camera as CameraDescription
from svelive.core.frame import Frame
from svelive.core.pattern import Pattern
from svelive.exr import REC709_CHROMATICITIES, read_exr
from svelive.simulation import exposure_scale, load_sample_scene, simulate
from tests.test_service_helpers import (PATTERN, SENSOR, Camera, PortReader, ServerThread, SimSource, make_camera,
                                        mjpeg_parts)

CFA = "RGGB"
#: The light as the camera sees it: strong red, weak blue.
WARM = np.float32([1.6, 1.0, 0.55])
SHAPE = (192, 224)


def colour_camera_description() -> CameraDescription:
    return CameraDescription.build(PATTERN, CFA, SENSOR)


def make_colour_camera(fps: float = 15.0, n: int = 4) -> Camera:
    """n raw RGGB frames of a shipped RGB scene under a warm light, panning sideways."""
    pattern = Pattern.parse(PATTERN)
    scene = np.maximum(load_sample_scene("desk", rgb=True), 0) * WARM
    scene = scene * exposure_scale(scene, pattern, SENSOR, stops_below_fill=1)
    rng = np.random.default_rng(0)
    raws = [simulate(np.ascontiguousarray(scene[:SHAPE[0], 4 * i:4 * i + SHAPE[1]]), pattern, SENSOR, cfa=CFA,
                     seed=rng).raw for i in range(n)]
    return Camera(fps=fps, raws=raws)


def colour_reference(raw: np.ndarray) -> np.ndarray:
    """What the service's single-frame reconstruction makes of a colour ``raw``: float32 (H, W, 3) camera RGB."""
    with Reconstructor(colour_camera_description(), temporal=False) as reconstructor:
        return reconstructor.process(raw).image


class ColourSimSource(SimSource):
    """SimSource with an RGGB camera: frames in BayerRG12."""

    def __init__(self, camera: Camera) -> None:
        super().__init__(camera)
        self.camera = colour_camera_description()

    def _next(self) -> Frame | None:
        frame = super()._next()
        return None if frame is None else dataclasses.replace(frame, pixel_format="BayerRG12")


class ColourServer(ServerThread):
    """ServerThread over a ColourSimSource (the same server, another source)."""

    def __init__(self, camera: Camera, **config) -> None:  # noqa: D107 - ServerThread's, with the colour source
        defaults = dict(source="sim", offline_after_s=0.6, retry_s=0.2, no_signal_fps=5.0, temporal=False)
        self.pipeline = Pipeline(PipelineConfig(**{**defaults, **config}), lambda: ColourSimSource(camera))
        settings = ServerSettings(port=0)
        self.sock = listen_socket(settings)
        self.port = self.sock.getsockname()[1]
        self.url = f"http://127.0.0.1:{self.port}"
        self.server = uvicorn.Server(uvicorn.Config(create_app(self.pipeline, settings), log_level="warning",
                                                    timeout_graceful_shutdown=1))
        self.thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.sock]}, daemon=True)


@pytest.fixture(scope="module")
def camera():
    return make_colour_camera()


@pytest.fixture(scope="module")
def server(camera):
    with ColourServer(camera) as srv:
        srv.wait_for(lambda s: s["frames"]["reconstructed"] > 2, timeout=60)
        yield srv


def decode(jpeg: bytes) -> np.ndarray:
    return cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_UNCHANGED)


def snapshot_exr(server: ServerThread, **params) -> tuple[dict[str, np.ndarray], dict[str, object]]:
    r = httpx.get(server.url + "/snapshot.exr", params=params, timeout=20)
    assert r.status_code == 200, r.text
    return read_exr(r.content)


def put(server: ServerThread, body: dict) -> httpx.Response:
    return httpx.put(server.url + "/api/settings", json=body, timeout=10)


def test_colour_stream_jpeg_and_state(server):
    with httpx.stream("GET", server.url + "/stream.mjpg", timeout=20) as r:
        assert r.status_code == 200
        parts = []
        for headers, body in mjpeg_parts(r):
            if headers["x-signal"] == "live":
                parts.append(body)
            if len(parts) == 3:
                break
    for body in parts:
        image = decode(body)
        assert image.shape == SHAPE + (3,)
        b, g, r_ = (image[:, :, c].astype(float) for c in range(3))
        # a colour scene, not a grey one: the channels really differ pixel by pixel
        assert np.mean(np.abs(r_ - b)) > 3 and np.mean(np.abs(r_ - g)) > 2
        assert 5 < image.mean() < 250
    snap = httpx.get(server.url + "/snapshot.jpg", timeout=20)
    assert snap.status_code == 200 and decode(snap.content).shape == SHAPE + (3,)
    state = server.state()
    assert state["cfa"] == CFA and state["output_space"] == "camera" and state["colour_matrix"] is None
    balance = state["white_balance"]
    assert balance["mode"] == "auto" and balance["multipliers"][1] == 1
    # the warm light (and the warm desk lamp of the scene) is seen and undone: red weakened, blue strengthened
    r_mult, _, b_mult = balance["multipliers"]
    assert r_mult < 1 < b_mult


def test_exr_snapshot_is_the_camera_rgb_frame(server, camera):
    channels, header = snapshot_exr(server)
    assert set(channels) == {"R", "G", "B"}
    expected = colour_reference(camera.delivered[int(header["frameId"])])
    np.testing.assert_array_equal(np.dstack([channels[c] for c in "RGB"]), expected)
    assert header["colourSpace"] == "camera" and header["whiteBalanceApplied"] == 0
    assert header["whiteBalanceMode"] == "auto" and header["cfa"] == CFA and "chromaticities" not in header
    assert header["whiteBalance"].shape == (3,) and header["whiteBalance"][1] == 1
    half, _ = snapshot_exr(server, half=1)
    assert set(half) == {"R", "G", "B"}


def test_white_balance_and_matrix_through_put_settings(server, camera):
    def channel_ratios() -> np.ndarray:
        """Mean red / green and blue / green of the preview, once the encoder has used the latest setting."""
        for _ in range(2):  # two snapshots: the second is encoded with the new setting
            image = decode(httpx.get(server.url + "/snapshot.jpg", timeout=20).content).astype(float)
            time.sleep(0.15)
        b, g, r_ = image.reshape(-1, 3).mean(axis=0)
        return np.array([r_ / g, b / g])

    try:
        auto = channel_ratios()
        r = put(server, {"white_balance": [1, 1, 1]})
        assert r.status_code == 200 and r.json()["white_balance"] == [1, 1, 1]
        neutral = channel_ratios()
        # the automatic balance brings the warm preview closer to grey in both ratios
        assert np.all(np.abs(np.log(auto)) < np.abs(np.log(neutral))), (auto, neutral)
        r = put(server, {"white_balance": "3,1,1"})
        assert r.status_code == 200 and r.json()["white_balance"] == [3, 1, 1]
        assert server.state()["white_balance"] == {"mode": "fixed", "multipliers": [3, 1, 1]}
        assert channel_ratios()[0] > 1.2 * neutral[0]  # the preview really got redder
        channels, header = snapshot_exr(server)
        assert header["whiteBalance"].tolist() == [3, 1, 1] and header["whiteBalanceMode"] == "fixed"
        assert header["whiteBalanceApplied"] == 0  # camera space: the data is the reconstruction itself

        matrix = [[1.5, -0.3, -0.2], [-0.2, 1.4, -0.2], [0.0, -0.4, 1.4]]
        r = put(server, {"colour_matrix": matrix, "output_space": "rec709", "white_balance": [2, 1, 1.5]})
        assert r.status_code == 200, r.text
        assert r.json()["output_space"] == "rec709" and len(r.json()["colour_matrix"]) == 9
        channels, header = snapshot_exr(server)
        assert header["colourSpace"] == "rec709" and header["whiteBalanceApplied"] == 1
        assert header["chromaticities"] == pytest.approx(REC709_CHROMATICITIES, abs=1e-6)
        np.testing.assert_allclose(header["colourMatrix"], matrix, rtol=1e-6)
        camera_rgb = colour_reference(camera.delivered[int(header["frameId"])])
        expected = np.einsum("ij,hwj->hwi", np.array(matrix) @ np.diag([2, 1, 1.5]), camera_rgb.astype(np.float64))
        np.testing.assert_allclose(np.dstack([channels[c] for c in "RGB"]), expected, rtol=1e-4, atol=1e-3)

        r = put(server, {"colour_matrix": None})  # rec709 without a matrix: refused, nothing applied
        assert r.status_code == 422 and "needs a colour matrix" in r.json()["detail"]
        assert server.pipeline.settings()["output_space"] == "rec709"
    finally:
        r = put(server, {"white_balance": "auto", "output_space": "camera", "colour_matrix": None})
        assert r.status_code == 200, r.text
    assert server.state()["white_balance"]["mode"] == "auto"


@pytest.mark.parametrize("body, words", [
    ({"white_balance": "warm"}, "'warm' is not a number"),
    ({"white_balance": [1, 2]}, "expected 3 numbers"),
    ({"white_balance": [1, -1, 1]}, "must be > 0"),
    ({"white_balance": [1, 1, 1000]}, "within"),
    ({"white_balance": None}, "cannot be null"),
    ({"white_balance": 5}, "white_balance"),
    ({"colour_matrix": [1, 0, 0, 0, 1, 0, 0, 0]}, "expected 9 numbers"),
    ({"colour_matrix": [[1, 2], [3, 4]]}, "shape"),
    ({"colour_matrix": "1,0,0,0,1,0,0,0,nan"}, "finite"),
    ({"output_space": "srgb"}, "camera, rec709"),
    ({"output_space": "rec709"}, "needs a colour matrix"),
    ({"colour": "red"}, "colour"),
    ({"jpeg_quality": 20, "white_balance": "x"}, "not a number"),
])
def test_bad_colour_settings_are_one_line_refusals(server, body, words):
    before = httpx.get(server.url + "/api/settings", timeout=5).json()
    r = put(server, body)
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert isinstance(detail, str) and "\n" not in detail and words in detail, detail
    assert httpx.get(server.url + "/api/settings", timeout=5).json() == before  # nothing half-applied


def test_mono_source_reports_no_colour():
    with ServerThread(make_camera(fps=15.0, n=2)) as srv:
        state = srv.wait_for(lambda s: s["frames"]["reconstructed"] > 0)
        assert state["cfa"] is None and state["white_balance"] is None and state["output_space"] == "camera"
        channels, header = snapshot_exr(srv)
        assert set(channels) == {"Y"} and "colourSpace" not in header


def test_pipeline_encodes_each_colour_frame_once_and_only_while_watched(camera):
    pipeline = Pipeline(PipelineConfig(source="sim", temporal=False), lambda: ColourSimSource(camera))
    assert pipeline.encoder.colour is pipeline.colour  # one colour stage for the preview (JPEG, RTSP) and the EXR
    with pipeline:
        deadline = time.monotonic() + 60
        while pipeline.reconstructed.count < 3:
            assert time.monotonic() < deadline and pipeline.reconstruction.error is None, pipeline.reconstruction.error
            time.sleep(0.05)
        assert pipeline.encoded.count == 0  # nobody watches: nothing encoded
        with PortReader(pipeline.jpeg_port) as reader:
            seen = reader.items
            pipeline.watch(+1)
            deadline = time.monotonic() + 20
            while len(seen) < 4:
                assert time.monotonic() < deadline
                time.sleep(0.05)
            pipeline.watch(-1)
        live = [item for item in seen if item.signal]
        assert len({item.hdr_seq for item in live}) == len(live)  # one JPEG per reconstructed frame
        assert decode(live[0].jpeg).shape == SHAPE + (3,)


def test_colour_with_temporal_fusion(camera):
    with ColourServer(camera, temporal=True) as srv:
        state = srv.wait_for(lambda s: s["frames"]["reconstructed"] > 3, timeout=60)
        assert state["reconstruct_error"] is None and state["temporal"] is True
        channels, header = snapshot_exr(srv)
        assert set(channels) == {"R", "G", "B"} and header["whiteBalanceMode"] == "auto"
        rgb = np.dstack([channels[c] for c in "RGB"])
        assert np.all(np.isfinite(rgb)) and rgb.min() >= 0
        image = decode(httpx.get(srv.url + "/snapshot.jpg", timeout=20).content)
        assert image.shape == SHAPE + (3,) and np.abs(image[:, :, 2].astype(float) - image[:, :, 0]).mean() > 3
