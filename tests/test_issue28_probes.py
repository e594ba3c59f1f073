"""Issue 28, probe defects 6-15: each against the real thing (a uvicorn server on a loopback port, the CLI
as a subprocess), each failing before its fix."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from tests.test_service_helpers import ServerThread, make_camera

RAGGED = [[1, 0, 0], [0, 1], [0, 0, 1]]


def run(*args: object, cwd: Path | None = None, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "svelive.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, cwd=cwd)


def one_line(text: str) -> str:
    lines = [line for line in text.strip().splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in text, text
    return lines[0]


def test_a_ragged_colour_matrix_is_a_422_with_one_line():
    with ServerThread(make_camera()) as server:
        r = httpx.put(server.url + "/api/settings", json={"colour_matrix": RAGGED}, timeout=10)
        assert r.status_code == 422, r.text
        detail = r.json()["detail"]
        assert isinstance(detail, str) and "\n" not in detail and "rows of different lengths" in detail, detail
        assert server.state()["frames"]["captured"] >= 0  # the server still answers


def test_a_ragged_colour_matrix_in_a_config_file_is_one_line(tmp_path):
    config = tmp_path / "svelive.json"
    config.write_text('{"colour_matrix": [[1, 0, 0], [0, 1], [0, 0, 1]]}')
    out = run("serve", "--config", config, "--port", "1", timeout=60)
    assert out.returncode == 2
    line = one_line(out.stderr)
    assert "rows of different lengths" in line and "inhomogeneous" not in line, line


@pytest.mark.parametrize("verb", [["calibrate", "response", "a.png", "b.png"],
                                  ["record", "--source", "demo", "--frames", "1", "-o", "x.sverec"]])
def test_equal_exposure_times_are_refused_by_the_cli_as_by_the_api(verb, tmp_path):
    for name in ("a.png", "b.png"):
        (tmp_path / name).write_bytes(b"")  # existing files: the times are what is wrong
    out = run(*verb, "--exposure-times", "1,1", cwd=tmp_path, timeout=60)
    assert out.returncode == 2 and "exposure times must differ" in out.stderr, out.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png", "b.png"]
