"""Issue 28.14: connections that hold a slot without asking for anything. A real ``svelive serve --rtsp``
(subprocess, loopback ports): 600 connections that send their headers slowly must not lock out ``/healthz``
(before: all 512 slots held for the 10 s header timeout, the health check refused), and the RTSP port keeps at
most 64 connections yet still lets a real client (ffmpeg) play (before: 300 held connections accepted)."""

from __future__ import annotations

import contextlib
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from tests.test_service_helpers import free_port, stop_process

MAX_CLIENTS = 64  # service.publishers.rtsp.MAX_CLIENTS


@pytest.fixture(scope="module")
def service(tmp_path_factory) -> Iterator[tuple[int, int, Path]]:
    """``svelive serve`` (small still demo, RTSP on) on two free loopback ports; yields (http_port, rtsp_port,
    the file its output goes to), so that a failure can say what the server said."""
    http_port, rtsp_port = free_port(), free_port()
    log = tmp_path_factory.mktemp("serve") / "serve.log"
    with open(log, "wb") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "svelive.cli", "serve", "--source", "demo", "--cfa", "none",
             "--source-option", "width=160", "--source-option", "height=96", "--source-option", "period_s=0",
             "--source-option", "fps=10", "--port", str(http_port), "--rtsp", str(rtsp_port)],
            stdout=out, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 300  # a first run on a machine compiles the kernels
        while not healthy(http_port):
            assert proc.poll() is None, f"serve exited: {tail(log)}"
            assert time.monotonic() < deadline, "serve did not answer /healthz in 300 s"
            time.sleep(0.3)
        yield http_port, rtsp_port, log
    finally:
        stop_process(proc)


def tail(log: Path, lines: int = 20) -> str:
    """The last ``lines`` lines the server wrote, for a failure's message."""
    return "\n".join(log.read_text(errors="replace").splitlines()[-lines:])


def healthy(port: int, timeout: float = 2.0) -> bool:
    try:
        return httpx.get(f"http://127.0.0.1:{port}/healthz", timeout=timeout).status_code == 200
    except httpx.HTTPError:
        return False


@contextlib.contextmanager
def held_connections(port: int, count: int, first_bytes: bytes) -> Iterator[list[socket.socket]]:
    """``count`` connections to ``port`` that send ``first_bytes`` and then nothing."""
    socks: list[socket.socket] = []
    try:
        for _ in range(count):
            s = socket.create_connection(("127.0.0.1", port), timeout=5)
            with contextlib.suppress(OSError):
                s.sendall(first_bytes)
            socks.append(s)
        yield socks
    finally:
        for s in socks:
            s.close()


def still_open(socks: list[socket.socket], settle_s: float = 1.5, at_most: int | None = None,
               within_s: float = 10.0) -> int:
    """How many of ``socks`` the server has not closed after ``settle_s`` s; with ``at_most``, polled for up to
    ``within_s`` s more until no more than that many are open (a server that closes the excess on its own event
    loop takes a while under load), then the count."""
    time.sleep(settle_s)
    deadline = time.monotonic() + within_s
    for s in socks:
        s.setblocking(False)
    open_ = [s for s in socks if not closed_by_peer(s)]
    while at_most is not None and len(open_) > at_most and time.monotonic() < deadline:
        time.sleep(0.25)
        open_ = [s for s in open_ if not closed_by_peer(s)]
    return len(open_)


def closed_by_peer(s: socket.socket) -> bool:
    """True when the peer closed ``s`` (what it sent before is read and dropped); ``s`` non-blocking."""
    while True:
        try:
            if s.recv(65536) == b"":
                return True
        except BlockingIOError:
            return False
        except OSError:
            return True


def test_slow_header_connections_do_not_lock_out_the_health_check(service):
    http_port, _, _ = service
    with held_connections(http_port, 600, b"GET /api/state HTTP/1.1\r\nHost: 127.0.0.1\r\n") as socks:
        started = time.monotonic()
        assert healthy(http_port, timeout=3), "/healthz unanswered with 600 slow-header connections open"
        assert time.monotonic() - started < 3
        assert still_open(socks, at_most=512) <= 512


@pytest.mark.skipif(shutil.which("ffmpeg") is None, reason="ffmpeg (the RTSP client) not installed")
def test_the_rtsp_port_caps_its_connections_and_still_serves_a_player(service):
    _, rtsp_port, log = service
    options = f"OPTIONS rtsp://127.0.0.1:{rtsp_port}/live RTSP/1.0\r\nCSeq: 1\r\n\r\n".encode()
    with held_connections(rtsp_port, 300, options) as socks:
        left = still_open(socks, at_most=MAX_CLIENTS)
        assert left <= MAX_CLIENTS, f"{left} RTSP connections open; the server said:\n{tail(log)}"
        out = subprocess.run(["ffmpeg", "-hide_banner", "-loglevel", "error", "-rtsp_transport", "tcp",
                              "-i", f"rtsp://127.0.0.1:{rtsp_port}/live", "-frames:v", "3", "-f", "null", "-"],
                             capture_output=True, text=True, timeout=30)
        assert out.returncode == 0, out.stderr
