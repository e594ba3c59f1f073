"""Several cameras in one service, Prometheus metrics, and the server's own bounds (token file, header
timeout, connection limit, tokens kept out of logs): real uvicorn servers on 127.0.0.1."""

from __future__ import annotations

import contextlib
import logging
import signal
import socket
import subprocess
import sys
import threading
import time

import cv2
import httpx
import numpy as np
import pytest
import uvicorn

from service.app import create_app, listen_socket
from service.commands import TokenRedactor
from service.pipeline import Pipeline, PipelineConfig
from service.protocol import bounded_protocol
from service.publishers.metrics import exposition, families
from service.settings import ServerSettings, read_config, resolve
from svelive.core.errors import SveliveError
from tests.test_service_helpers import SimSource, make_camera

SIM = dict(source="sim", offline_after_s=0.6, retry_s=0.2, no_signal_fps=5.0, temporal=False)


class MultiServer:
    """A real uvicorn server over named pipelines, each on its own simulated camera."""

    def __init__(self, cameras: dict, protocol=None, **server) -> None:
        self.pipelines = {name: Pipeline(PipelineConfig(**SIM), (lambda c=cam: SimSource(c)))
                          for name, cam in cameras.items()}
        settings = ServerSettings(port=0, **server)
        self.sock = listen_socket(settings)
        self.port = self.sock.getsockname()[1]
        self.url = f"http://127.0.0.1:{self.port}"
        extra = {} if protocol is None else {"http": protocol}
        self.server = uvicorn.Server(uvicorn.Config(create_app(self.pipelines, settings), log_level="warning",
                                                    timeout_graceful_shutdown=1, **extra))
        self.thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.sock]}, daemon=True)

    def __enter__(self) -> MultiServer:
        self.thread.start()
        deadline = time.monotonic() + 10
        while not self.server.started:
            assert time.monotonic() < deadline and self.thread.is_alive(), "uvicorn did not start"
            time.sleep(0.02)
        return self

    def __exit__(self, *exc: object) -> None:
        self.server.should_exit = True
        self.thread.join(10)
        self.sock.close()


def wait_state(url: str, predicate, timeout: float = 10.0, **kwargs) -> dict:
    deadline = time.monotonic() + timeout
    while True:
        state = httpx.get(url, timeout=5, **kwargs).json()
        if predicate(state):
            return state
        assert time.monotonic() < deadline, f"state never satisfied the condition: {state}"
        time.sleep(0.1)


def test_each_camera_at_its_own_path_and_the_first_at_the_root():
    small, wide = make_camera(shape=(96, 128)), make_camera(shape=(64, 192))
    with MultiServer({"dock": small, "yard": wide}) as srv:
        for name, cam in (("dock", small), ("yard", wide)):
            wait_state(f"{srv.url}/cam/{name}/api/state", lambda s: s["frames"]["reconstructed"] > 0)
        sizes = {}
        for path in ("/cam/dock", "/cam/yard", ""):
            r = httpx.get(f"{srv.url}{path}/snapshot.jpg", timeout=5)
            assert r.status_code == 200
            sizes[path] = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_UNCHANGED).shape[:2]
        assert sizes == {"/cam/dock": (96, 128), "/cam/yard": (64, 192), "": (96, 128)}
        assert httpx.get(f"{srv.url}/cam/yard/api/state", timeout=5).json()["camera_name"] == "yard"
        assert httpx.get(f"{srv.url}/api/state", timeout=5).json()["camera_name"] == "dock"
        viewer = httpx.get(f"{srv.url}/cam/yard/", timeout=5)
        assert viewer.status_code == 200 and 'fetch("api/state"' in viewer.text  # relative: stays under /cam/yard/
        assert httpx.get(f"{srv.url}/cam/nope/api/state", timeout=5).status_code == 404
        health = httpx.get(f"{srv.url}/healthz", timeout=5).json()
        assert health["cameras"] == {"dock": "online", "yard": "online"}


def test_one_camera_offline_never_stalls_another():
    down, up = make_camera(), make_camera()
    with MultiServer({"down": down, "up": up}) as srv:
        wait_state(f"{srv.url}/cam/down/api/state", lambda s: s["frames"]["reconstructed"] > 0)
        down.plugged = False
        wait_state(f"{srv.url}/cam/down/api/state", lambda s: not s["source"]["online"])
        before = httpx.get(f"{srv.url}/cam/up/api/state", timeout=5).json()["frames"]["reconstructed"]
        after = wait_state(f"{srv.url}/cam/up/api/state", lambda s: s["frames"]["reconstructed"] >= before + 10)
        assert after["source"]["online"]
        assert httpx.get(f"{srv.url}/healthz", timeout=5).json()["cameras"] == {"down": "offline", "up": "online"}


def test_metrics_tell_the_state_of_every_camera():
    with MultiServer({"a": make_camera(), "b": make_camera()}, token="s3cret") as srv:
        auth = {"Authorization": "Bearer s3cret"}
        wait_state(f"{srv.url}/cam/b/api/state", lambda s: s["frames"]["reconstructed"] > 2, headers=auth)
        assert httpx.get(f"{srv.url}/metrics", timeout=5).status_code == 401
        r = httpx.get(f"{srv.url}/metrics", headers=auth, timeout=5)
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
        text = r.text
        state = httpx.get(f"{srv.url}/cam/b/api/state", headers=auth, timeout=5).json()
    samples = {}
    for line in text.splitlines():
        if line and not line.startswith("#"):
            name, value = line.rsplit(" ", 1)
            samples[name] = float(value)
    for cam in ("a", "b"):
        assert samples[f'svelive_source_online{{camera="{cam}"}}'] == 1.0
        assert samples[f'svelive_frames_total{{camera="{cam}",stage="reconstructed"}}'] > 0
    # the scrape came before the state: its counter cannot be ahead of it
    assert samples['svelive_frames_total{camera="b",stage="captured"}'] <= state["frames"]["captured"]
    assert "svelive_process_resident_memory_bytes" in text


def test_metrics_public_needs_no_token():
    with MultiServer({"a": make_camera()}, token="s3cret", metrics_public=True) as srv:
        assert httpx.get(f"{srv.url}/metrics", timeout=5).status_code == 200
        assert httpx.get(f"{srv.url}/api/state", timeout=5).status_code == 401


def test_metric_families_from_a_state():
    state = {"frames": {"captured": 10, "reconstructed": 9, "encoded": 4, "streamed": 3},
             "fps": {"captured": 30.0}, "drops": {"reconstruct_busy": 1},
             "source": {"online": False, "reconnects": 2, "spec": "demo"}, "clients": 2,
             "noise": {"gain": 2.5, "read_noise": 1.2, "gain_sigma": 0.1, "read_noise_sigma": 0.05},
             "white_balance": {"multipliers": [2.0, 1.0, 1.5]}, "pattern": "1,4/16,64", "cfa": "RGGB",
             "warming_up": True,
             "live_quality": {"mode": "adaptive", "step": 1, "name": "weighted+fusion",
                              "steps": ["adaptive+fusion", "weighted+fusion", "weighted"]}}
    text = exposition(families({"x": state}, {"x": {"reconstruct": ([(10.0, 3), (50.0, 5)], 120.0, 6)}}),
                      process=False).decode()
    assert 'svelive_drops_total{camera="x",cause="reconstruct_busy"} 1.0' in text
    assert 'svelive_source_online{camera="x"} 0.0' in text
    assert 'svelive_noise_estimate{camera="x",quantity="read_noise"} 1.2' in text
    assert 'svelive_white_balance{camera="x",channel="b"} 1.5' in text
    assert 'svelive_stage_latency_seconds_bucket{camera="x",le="0.05",stage="reconstruct"} 5.0' in text
    assert 'svelive_stage_latency_seconds_bucket{camera="x",le="+Inf",stage="reconstruct"} 6.0' in text
    assert 'svelive_stage_latency_seconds_sum{camera="x",stage="reconstruct"} 0.12' in text
    assert 'svelive_warming_up{camera="x"} 1.0' in text
    # the step's index under labels that do not change with it, and one series per step of the ladder
    assert 'svelive_live_quality_step{camera="x",mode="adaptive"} 1.0' in text
    assert 'svelive_live_quality{camera="x",step_name="weighted+fusion"} 1.0' in text
    assert 'svelive_live_quality{camera="x",step_name="adaptive+fusion"} 0.0' in text
    assert 'svelive_live_quality{camera="x",step_name="weighted"} 0.0' in text
    ready = exposition(families({"x": {**state, "warming_up": False}}), process=False).decode()
    assert 'svelive_warming_up{camera="x"} 0.0' in ready


def write(path, text: str) -> str:
    path.write_text(text)
    return str(path)


def test_camera_list_in_the_config_file(tmp_path):
    config = write(tmp_path / "svelive.toml", """
jpeg_quality = 70
port = 9100
[[cameras]]
name = "dock"
source = "demo"
source_options = { width = 320, height = 240 }
[[cameras]]
name = "yard"
source = "demo"
jpeg_quality = 90
""")
    settings = resolve({"method": "aggregate"}, {}, config=config)
    named = settings.named_pipelines()
    assert list(named) == ["dock", "yard"] and settings.server.port == 9100
    assert named["dock"].source_options == {"width": 320, "height": 240} and named["yard"].source_options == {}
    assert (named["dock"].jpeg_quality, named["yard"].jpeg_quality) == (70, 90)  # the camera's table wins over the top
    assert named["dock"].method == named["yard"].method == "aggregate"  # the command line reaches every camera
    assert settings.pipeline == named["dock"]
    assert list(resolve({}, {}).named_pipelines()) == ["main"]


@pytest.mark.parametrize("tables, message", [
    ('[[cameras]]\nname = "a"\n[[cameras]]\nname = "a"\n', "used twice"),
    ('[[cameras]]\nname = "Big Name"\n', "lower-case"),
    ('[[cameras]]\nname = "a"\nport = 1\n', "belong to the server"),
    ('[[cameras]]\nname = "a"\nframerate = 1\n', "unknown setting 'framerate'"),
    ('cameras = 3\n', "list of tables"),
])
def test_bad_camera_lists_are_refused_in_one_line(tmp_path, tables, message):
    with pytest.raises(SveliveError, match=message) as caught:
        read_config(write(tmp_path / "c.toml", tables))
    assert "\n" not in str(caught.value)


def test_source_on_the_command_line_conflicts_with_a_camera_list(tmp_path):
    config = write(tmp_path / "c.toml", '[[cameras]]\nname = "a"\nsource = "demo"\n')
    with pytest.raises(SveliveError, match="set them in each"):
        resolve({"source": "demo"}, {}, config=config)


def test_token_file(tmp_path):
    path = write(tmp_path / "token", "  abc123  \nignored\n")
    assert ServerSettings(token_file=path).token == "abc123"
    assert resolve({}, {"SVELIVE_TOKEN_FILE": path}).server.token == "abc123"
    with pytest.raises(SveliveError, match="empty"):
        ServerSettings(token_file=write(tmp_path / "empty", "\n"))
    with pytest.raises(SveliveError, match="does-not-exist"):
        ServerSettings(token_file=str(tmp_path / "does-not-exist"))
    with pytest.raises(SveliveError, match="not both"):
        ServerSettings(token="x", token_file=path)


def test_tokens_are_kept_out_of_access_logs():
    record = logging.LogRecord("uvicorn.access", logging.INFO, __file__, 1, '%s - "%s %s HTTP/%s" %d',
                               ("127.0.0.1:5", "GET", "/stream.mjpg?fps=2&token=hunter2", "1.1", 200), None)
    assert TokenRedactor().filter(record)
    assert "hunter2" not in record.getMessage() and "token=***" in record.getMessage()
    assert "fps=2" in record.getMessage()


def closed_within(sock: socket.socket, seconds: float) -> bool:
    """True if the peer closes ``sock`` within ``seconds``."""
    sock.settimeout(seconds)
    try:
        return sock.recv(1024) == b""
    except (TimeoutError, socket.timeout):
        return False
    except ConnectionResetError:
        return True


def test_half_sent_headers_are_cut_off_and_connections_bounded():
    with MultiServer({"a": make_camera()}, protocol=bounded_protocol(0.5, 8)) as srv:
        wait_state(f"{srv.url}/api/state", lambda s: s["frames"]["reconstructed"] > 0)  # /healthz ready from then on
        slow = socket.create_connection(("127.0.0.1", srv.port))
        slow.sendall(b"GET /api/state HTTP/1.1\r\nHost: 127.0.0.1\r\n")  # and never the blank line
        assert closed_within(slow, 5.0)
        slow.close()
        trickle = socket.create_connection(("127.0.0.1", srv.port))  # whole headers, then a body that never ends
        trickle.sendall(b"PUT /api/settings HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
                        b"Content-Length: 100\r\n\r\n{\"jpeg")
        assert closed_within(trickle, 5.0)
        trickle.close()
        # a whole request in time is answered, and the connection kept alive for the next one
        with httpx.Client(base_url=srv.url, timeout=5) as client:
            assert client.get("/healthz").status_code == 200
            time.sleep(0.2)
            assert client.get("/healthz").status_code == 200
        held = [socket.create_connection(("127.0.0.1", srv.port)) for _ in range(12)]
        try:
            refused = sum(closed_within(s, 0.3) for s in held)
            assert refused >= 12 - 8  # beyond the bound: closed at once, long before the header timeout
        finally:
            for s in held:
                s.close()
        assert httpx.get(f"{srv.url}/healthz", timeout=5).status_code == 200  # and the server still serves


def two_demo_cameras(tmp_path, port: int) -> str:
    """A config file serving on ``port`` a colour demo camera "one" (160x96) and a monochrome "two" (128x64)."""
    return write(tmp_path / "cams.toml", f"""
port = {port}
[[cameras]]
name = "one"
source = "demo"
source_options = {{ width = 160, height = 96, fps = 10 }}
[[cameras]]
name = "two"
source = "demo"
cfa = "none"
pattern = "1,4/16,64"
source_options = {{ width = 128, height = 64, fps = 10 }}
""")


@contextlib.contextmanager
def serving(args: list[str], port: int):
    """``svelive serve ARGS`` in a child process, once /healthz answers on ``port``; yields the process, whose
    stderr is in ``.err`` after SIGTERM ended it."""
    proc = subprocess.Popen([sys.executable, "-m", "svelive.cli", "serve", *args], stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                if httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=2).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert proc.poll() is None and time.monotonic() < deadline, "svelive serve did not start"
            time.sleep(0.2)
        yield proc
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            _, proc.err = proc.communicate(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            _, proc.err = proc.communicate()


def test_serve_two_demo_cameras_from_a_config_file(tmp_path):
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    config = two_demo_cameras(tmp_path, port)
    token = write(tmp_path / "token", "t0ken\n")
    with serving(["--config", config, "--token-file", token], port) as proc:
        auth = {"Authorization": "Bearer t0ken"}
        for name, shape in (("one", (96, 160)), ("two", (64, 128))):
            wait_state(f"http://127.0.0.1:{port}/cam/{name}/api/state",
                       lambda s: s["frames"]["reconstructed"] > 0, timeout=30, headers=auth)
            r = httpx.get(f"http://127.0.0.1:{port}/cam/{name}/snapshot.jpg", headers=auth, timeout=5)
            assert cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_UNCHANGED).shape[:2] == shape
        assert httpx.get(f"http://127.0.0.1:{port}/cam/one/api/state", timeout=5).status_code == 401
    err = proc.err
    assert "/cam/two/" in err and "t0ken" not in err


def test_serve_rtsp_for_each_camera_on_one_port_listed_in_the_state(tmp_path):
    from tests.test_service_rtsp import MISSING

    if MISSING is not None:
        pytest.skip(f"GStreamer RTSP server not installed: {MISSING}")
    ports = []
    for _ in range(3):
        with socket.socket() as probe:
            probe.bind(("127.0.0.1", 0))
            ports.append(probe.getsockname()[1])
    port, rtsp_port = ports[0], max(ports[1:]) + 100
    config = two_demo_cameras(tmp_path, port)

    def decode(url: str, shape: tuple[int, int]) -> None:
        # ffmpeg, a client of its own (not GStreamer's): two decoded grey frames of the camera's size
        decoded = subprocess.run(["ffmpeg", "-v", "error", "-rtsp_transport", "tcp", "-i", url, "-frames:v", "2",
                                  "-f", "rawvideo", "-pix_fmt", "gray", "-"], capture_output=True, timeout=60)
        assert decoded.returncode == 0, decoded.stderr.decode()[-300:]
        assert len(decoded.stdout) == 2 * shape[0] * shape[1]

    with serving(["--config", config, "--rtsp", str(rtsp_port), "--token", "tok"], port) as proc:
        auth = {"Authorization": "Bearer tok"}
        for name, shape in (("one", (96, 160)), ("two", (64, 128))):
            state = wait_state(f"http://127.0.0.1:{port}/cam/{name}/api/state",
                               lambda s: s["frames"]["reconstructed"] > 0, timeout=30, headers=auth)
            # every camera on the one port, at its own path
            assert state["rtsp"]["url"] == f"rtsp://127.0.0.1:{rtsp_port}/cam/{name}" and state["rtsp"]["auth"]
            decode(state["rtsp"]["url"].replace("rtsp://", "rtsp://viewer:tok@"), shape)
            refused = subprocess.run(["ffmpeg", "-v", "error", "-rtsp_transport", "tcp", "-i", state["rtsp"]["url"],
                                      "-frames:v", "1", "-f", "null", "-"], capture_output=True, timeout=60)
            assert refused.returncode != 0 and b"401" in refused.stderr
        # the first camera is also at /live, the same media as /cam/one
        decode(f"rtsp://viewer:tok@127.0.0.1:{rtsp_port}/live", (96, 160))
        state = httpx.get(f"http://127.0.0.1:{port}/cam/one/api/state", headers=auth, timeout=5).json()
        assert state["rtsp"]["paths"] == ["/cam/one", "/live"]
        metrics = httpx.get(f"http://127.0.0.1:{port}/metrics", headers=auth, timeout=5).text
        assert 'svelive_clients{camera="two",kind="rtsp"}' in metrics
    err = proc.err
    assert (f"one as RTSP on rtsp://127.0.0.1:{rtsp_port}/live and rtsp://127.0.0.1:{rtsp_port}/cam/one" in err
            and f"two as RTSP on rtsp://127.0.0.1:{rtsp_port}/cam/two" in err)


def test_latency_histograms_count_every_duration():
    from service.pipeline.meters import LatencyWindow

    window = LatencyWindow()
    for ms in (0.5, 1.0, 3.0, 40.0, 40.0, 7000.0):
        window.add(ms)
    buckets, total, count = window.histogram()
    as_dict = dict(buckets)
    assert (as_dict[1.0], as_dict[2.0], as_dict[5.0], as_dict[50.0], as_dict[5000.0]) == (2, 2, 3, 5, 5)
    assert count == 6 and total == sum((0.5, 1.0, 3.0, 40.0, 40.0, 7000.0))
    text = exposition(families({"c": {"frames": {}}}, {"c": {"reconstruct": window.histogram()}}), process=False)
    assert b'svelive_stage_latency_seconds_bucket{camera="c",le="+Inf",stage="reconstruct"} 6.0' in text
