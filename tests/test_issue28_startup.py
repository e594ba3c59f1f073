"""Issue 28.2 and 28.4: a first start that speaks. ``svelive serve`` with an empty kernel cache (a first start
on a machine compiles for minutes) says what it does at once, and a busy HTTP or RTSP port is refused before
the compiling, not after it (before: silence, and the port's error after the whole warm-up). The set-up's
apt-get waits for a package lock another apt job holds, saying so (before: apt-get update failed at once)."""

from __future__ import annotations

import fcntl
import os
import shutil
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def cold_serve(tmp_path: Path, *args: object) -> subprocess.Popen:
    """``svelive serve ARGS`` with an empty numba cache: every kernel would compile."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba-cache")}
    return subprocess.Popen([sys.executable, "-m", "svelive.cli", "serve", "--source", "demo", *map(str, args)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)


def stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.kill()
    proc.wait(10)


@pytest.mark.parametrize("busy", ["--port", "--rtsp"])
def test_a_busy_port_is_refused_before_the_kernels_compile(busy, tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        other = ["--rtsp", "0"] if busy == "--port" else ["--port", "0"]
        proc = cold_serve(tmp_path, busy, port, *other)
        try:
            _, err = proc.communicate(timeout=40)  # the compile alone takes minutes
        finally:
            stop(proc)
    assert proc.returncode == 2, err
    assert f"127.0.0.1:{port}" in err and "cannot listen" in err and "Traceback" not in err, err


def test_the_warm_up_says_what_it_does_at_once(tmp_path):
    proc = cold_serve(tmp_path, "--port", "0")
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stderr), daemon=True)
    reader.start()
    try:
        deadline = time.monotonic() + 30
        while not any("preparing the reconstruction kernels" in line for line in lines):
            assert proc.poll() is None and time.monotonic() < deadline, f"nothing said in 30 s: {lines}"
            time.sleep(0.2)
    finally:
        stop(proc)
    said = next(line for line in lines if "preparing the reconstruction kernels" in line)
    assert said.startswith("svelive serve: ") and "minutes" in said, said


@pytest.mark.skipif(shutil.which("apt-get") is None or os.geteuid() != 0, reason="needs apt-get, as root")
def test_apt_get_waits_for_a_package_lock_another_job_holds(tmp_path):
    """A real apt-get update on lists of its own (no sources: no network), whose lock this test holds 4 s."""
    lists = tmp_path / "lists"
    for folder in (lists / "partial", tmp_path / "parts", tmp_path / "cache" / "archives" / "partial"):
        folder.mkdir(parents=True)
    lock = os.open(lists / "lock", os.O_RDWR | os.O_CREAT)
    fcntl.lockf(lock, fcntl.LOCK_EX)
    threading.Timer(4.0, lambda: (fcntl.lockf(lock, fcntl.LOCK_UN), os.close(lock))).start()
    started = time.monotonic()
    out = subprocess.run([ROOT / "scripts" / "apt-get.sh", "-o", f"Dir::State::Lists={lists}",
                          "-o", "Dir::Etc::SourceList=/dev/null", "-o", f"Dir::Etc::SourceParts={tmp_path / 'parts'}",
                          "-o", f"Dir::Cache={tmp_path / 'cache'}", "update", "-q"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert time.monotonic() - started >= 3.5
    assert "another apt job holds the package lock" in out.stderr and "waiting" in out.stderr, out.stderr
