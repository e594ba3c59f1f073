"""Issue 28.11: ``replay-info`` reads every frame and lists those whose data is damaged (before: a recording
with a bit-flipped frame was reported with ``"damaged_records": []`` while ``export`` skipped the frame), and
a recording's problems print as one plain line each (before: Python's ``UserWarning`` with the file, line
and source code of the call, in the CLI and in the replay source of the service)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from replay import RecordingReader
from replay.container import RECORD_HEADER


def svelive(*args: object) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "svelive.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=120)


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("rec") / "run.sverec"
    out = svelive("record", "--source", "demo", "--cfa", "none", "--width", "64", "--height", "48", "--frames", 6,
                  "-o", path, "--overwrite", "-q")
    assert out.returncode == 0, out.stderr
    return path


def flipped(recording: Path, folder: Path, frames: tuple[int, ...]) -> Path:
    """A copy of ``recording`` with one byte of each of ``frames``' data inverted (its index intact)."""
    with RecordingReader(recording) as r:
        start, record = r.layout.data_offset, r.layout.record_size
    data = bytearray(recording.read_bytes())
    for i in frames:
        data[start + i * record + RECORD_HEADER.size + 100] ^= 0xFF
    path = folder / "flipped.sverec"
    path.write_bytes(data)
    return path


def plain_warnings(stderr: str) -> list[str]:
    """The warning lines of ``stderr``, asserting that there is no Python warning and no source line."""
    assert "UserWarning" not in stderr and "warnings.warn" not in stderr and "warn(" not in stderr, stderr
    assert not any(line.startswith(" ") for line in stderr.splitlines()), stderr
    return [line for line in stderr.splitlines() if line.startswith("svelive: warning: ")]


def test_replay_info_lists_frames_with_damaged_data(recording: Path, tmp_path: Path) -> None:
    path = flipped(recording, tmp_path, (1, 4))
    out = svelive("replay-info", path, "-q")
    assert out.returncode == 0, out.stderr
    info = json.loads(out.stdout)
    assert info["damaged_records"] == [1, 4]
    assert info["verified"] == {"frames": 6, "intact": 4, "damaged": [1, 4]}
    assert any("2 of 6 frames damaged" in w and "1, 4" in w for w in info["warnings"]), info["warnings"]
    assert len(plain_warnings(out.stderr)) == 1
    assert svelive("replay-info", path, "--verify", "-q").returncode == 1
    assert json.loads(svelive("replay-info", recording, "-q").stdout)["damaged_records"] == []


def test_unclean_recording_warns_in_one_plain_line(recording: Path, tmp_path: Path) -> None:
    with RecordingReader(recording) as r:
        start, record = r.layout.data_offset, r.layout.record_size
    torn = tmp_path / "torn.sverec"
    torn.write_bytes(recording.read_bytes()[: start + 3 * record + record // 2])  # a recorder killed mid-frame
    out = svelive("replay-info", torn, "-q")
    assert out.returncode == 0, out.stderr
    lines = plain_warnings(out.stderr)
    assert len(lines) == 2 and "torn last frame" in out.stderr and "no index" in out.stderr, out.stderr
    assert all(str(torn) in line for line in lines)


def test_replay_source_warns_in_one_plain_line(recording: Path, tmp_path: Path) -> None:
    """The replay source (what ``svelive serve --source replay:`` and ``reconstruct-sequence`` read) reports
    a damaged frame it skips in one plain line, with the display the ``svelive`` command installs; importing
    the library alone leaves Python's warning display as it was."""
    path = flipped(recording, tmp_path, (2,))
    code = ("import sys, warnings; before = warnings.showwarning\n"
            "from svelive.capture import open_source; import replay.reader\n"
            "assert warnings.showwarning is before, 'the import changed the warning display'\n"
            "replay.reader.show_warnings_plainly()  # as svelive.cli.main does\n"
            f"with open_source('replay:{path}', speed=0) as s: n = sum(1 for _ in s)\n"
            "print(n)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.strip() == "5", out.stderr
    lines = plain_warnings(out.stderr)
    assert lines == [f"svelive: warning: {path}: frame 2 checksum mismatch (damaged data)"], out.stderr
