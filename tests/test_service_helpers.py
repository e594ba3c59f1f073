"""Shared parts of the service tests: a controllable simulated camera, a real uvicorn server, an MJPEG reader.

(No tests here; the module name only makes pytest import it like the others.)
"""

from __future__ import annotations

import dataclasses
import socket
import subprocess
import threading
import time
from collections.abc import Iterator

import httpx
import numpy as np
import uvicorn

from service.app import create_app, listen_socket
from service.pipeline import Pipeline, PipelineConfig
from service.settings import ServerSettings
from svelive import Reconstructor, Sensor
from svelive.capture import Source
from svelive.core.camera import Camera as CameraDescription
from svelive.core.errors import SveliveError
from svelive.core.frame import Frame
from svelive.core.pattern import Pattern
from svelive.simulation import exposure_scale, load_sample_scene, simulate

PATTERN = "1,4/16,64"
SENSOR = Sensor.from_full_well(12, 10_000, 3)


class PortReader:
    """Takes every new item of a pipeline port (a ``service.pipeline.Newest``) in a thread of its own, as a
    publisher does, into ``items`` (a context manager: reads between enter and exit)."""

    def __init__(self, port) -> None:
        self.port = port
        self.items: list = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, daemon=True)

    def _read(self) -> None:
        seen = self._seen
        while not self._stop.is_set():
            got = self.port.get_newest(seen, 0.05)
            if got is not None:
                seen, item = got
                self.items.append(item)

    def __enter__(self) -> PortReader:
        self._seen = self.port.seq  # what comes after the enter
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join(5)


def reference_image(raw: np.ndarray, pattern: Pattern | str = PATTERN, response=None) -> np.ndarray:
    """What the service's single-frame reconstruction (no temporal fusion, default method) makes of ``raw``."""
    camera = CameraDescription(Pattern.parse(pattern), sensor=SENSOR, response=response)
    with Reconstructor(camera, temporal=False) as reconstructor:
        return reconstructor.process(raw).image


@dataclasses.dataclass
class Camera:
    """What the simulated camera is doing; tests flip these from their own thread.

    plugged: False makes the open source fail and new opens raise (a camera unplugged).
    paused: True makes it deliver nothing while staying connected (a stalled camera).
    """

    fps: float = 20.0
    plugged: bool = True
    paused: bool = False
    raws: list[np.ndarray] = dataclasses.field(default_factory=list)
    delivered: dict[int, np.ndarray] = dataclasses.field(default_factory=dict)
    opens: int = 0


def make_camera(fps: float = 20.0, n: int = 6, shape: tuple[int, int] = (192, 224)) -> Camera:
    """A camera replaying n simulated raw frames of a shipped scene panning sideways."""
    pattern = Pattern.parse(PATTERN)
    scene = load_sample_scene("desk")
    scene = np.maximum(scene, 0) * exposure_scale(scene, pattern, SENSOR, stops_below_fill=1)
    rng = np.random.default_rng(0)
    raws = []
    for i in range(n):
        crop = scene[:shape[0], 4 * i:4 * i + shape[1]]
        raws.append(simulate(np.ascontiguousarray(crop), pattern, SENSOR, seed=rng).raw)
    return Camera(fps=fps, raws=raws)


def chart_raws(curve: str = "gamma2.2", n: int = 2, shape: tuple[int, int] = (192, 224)) -> list[np.ndarray]:
    """n raw frames of a grey-patch chart (10 stops) seen through a camera with a non-linear response ``curve``."""
    from svelive.calibrate import CURVES, simulate_nonlinear

    rng = np.random.default_rng(5)
    patches = np.kron(2.0 ** rng.uniform(-10, 0, (shape[0] // 16, shape[1] // 16)), np.ones((16, 16)))
    scene = (patches * SENSOR.range_dn / patches.max()).astype(np.float32)
    return [simulate_nonlinear(scene, PATTERN, SENSOR, CURVES[curve], seed=i) for i in range(n)]


class SimSource(Source):
    """A Source over a Camera: frames at camera.fps, cycling through camera.raws."""

    poll_s = 0.05

    def __init__(self, camera: Camera) -> None:
        super().__init__("sim", pattern=PATTERN, sensor=SENSOR)
        self.sim = camera
        self._n = 0
        self._next_t = 0.0

    def _open(self) -> None:
        if not self.sim.plugged:
            raise SveliveError("sim: camera not found")
        self.sim.opens += 1
        self._next_t = time.monotonic()

    def _next(self) -> Frame | None:
        cam = self.sim
        if not cam.plugged:
            raise SveliveError("sim: camera disconnected")
        wait = self._next_t - time.monotonic()
        if wait > 0 and not self._wait(min(wait, self.poll_s)):
            return None
        if time.monotonic() < self._next_t or cam.paused:
            if cam.paused:
                self._wait(self.poll_s)
            return None
        self._next_t = max(self._next_t + 1.0 / cam.fps, time.monotonic() - 1.0)
        raw = cam.raws[self._n % len(cam.raws)]
        frame = Frame(raw=raw, frame_id=self._n, host_time_ns=time.monotonic_ns(), pixel_format="Mono12",
                      camera=self.camera)
        cam.delivered[self._n] = raw
        self._n += 1
        return frame


class ServerThread:
    """A real uvicorn server on a free 127.0.0.1 port, in a thread, over a Pipeline on a Camera.

    ``server``: more ServerSettings (``cors_origins``, ``allowed_hosts``...).
    """

    def __init__(self, camera: Camera, token: str | None = None, send_buffer_kb: int = 256,
                 server: dict | None = None, **config) -> None:
        defaults = dict(source="sim", offline_after_s=0.6, retry_s=0.2, no_signal_fps=5.0, temporal=False)
        self.pipeline = Pipeline(PipelineConfig(**{**defaults, **config}), lambda: SimSource(camera))
        settings = ServerSettings(port=0, token=token, send_buffer_kb=send_buffer_kb, **(server or {}))
        self.sock = listen_socket(settings)
        self.port = self.sock.getsockname()[1]
        self.url = f"http://127.0.0.1:{self.port}"
        self.app = app = create_app(self.pipeline, settings)
        self.server = uvicorn.Server(uvicorn.Config(app, log_level="warning", timeout_graceful_shutdown=1))
        self.thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.sock]}, daemon=True)

    def __enter__(self) -> ServerThread:
        self.thread.start()
        deadline = time.monotonic() + 10
        while not self.server.started:
            if time.monotonic() > deadline or not self.thread.is_alive():
                raise RuntimeError("uvicorn did not start")
            time.sleep(0.02)
        return self

    def __exit__(self, *exc: object) -> None:
        app = getattr(self, "app", None) or self.server.config.app
        shutdown_streams = getattr(app.state, "shutdown_streams", None)
        if shutdown_streams is not None:  # what a SIGTERM does first in `svelive serve`
            shutdown_streams()
        self.server.should_exit = True
        self.thread.join(10)
        self.sock.close()

    def state(self, **kwargs) -> dict:
        r = httpx.get(self.url + "/api/state", timeout=5, **kwargs)
        r.raise_for_status()
        return r.json()

    def wait_for(self, predicate, timeout: float = 8.0, **kwargs) -> dict:
        """Poll /api/state until predicate(state) holds; returns that state (AssertionError on timeout)."""
        deadline = time.monotonic() + timeout
        while True:
            state = self.state(**kwargs)
            if predicate(state):
                return state
            if time.monotonic() > deadline:
                raise AssertionError(f"state never satisfied the condition: {state}")
            time.sleep(0.1)


def mjpeg_parts(response: httpx.Response) -> Iterator[tuple[dict[str, str], bytes]]:
    """(headers, body) of each part of a multipart/x-mixed-replace response, checking the framing."""
    boundary = response.headers["content-type"].split("boundary=")[1].encode()
    buffer = b""
    chunks = response.iter_raw()

    def fill(n: int) -> None:
        nonlocal buffer
        while len(buffer) < n:
            buffer += next(chunks)

    while True:
        while b"\r\n\r\n" not in buffer:
            buffer += next(chunks)
        head, buffer = buffer.split(b"\r\n\r\n", 1)
        lines = head.decode("latin-1").split("\r\n")
        assert lines[0] == "--" + boundary.decode(), lines[0]
        headers = {k.strip().lower(): v.strip() for k, v in (line.split(":", 1) for line in lines[1:])}
        length = int(headers["content-length"])
        fill(length + 2)
        body, tail, buffer = buffer[:length], buffer[length:length + 2], buffer[length + 2:]
        assert tail == b"\r\n"
        yield headers, body


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now (for a server started in another process)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def stop_process(proc: subprocess.Popen, grace_s: float = 10.0) -> None:
    """Stop a child process: SIGTERM, then SIGKILL after ``grace_s`` seconds; reaped either way."""
    if proc.poll() is not None:
        return
    proc.terminate()
    try:
        proc.wait(grace_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(5)
