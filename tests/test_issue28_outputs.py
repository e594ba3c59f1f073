"""Issue 28.10: an output that cannot be written (a FIFO, a link, a directory, a missing folder) is refused
before any work: ``calibrate response`` on the README's frame says only that (before: every fit ran first, its
progress lines before the refusal); ``reconstruct`` and ``simulate`` given an input that does not exist name
the output, not the input (before: the input was read first)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest


def bad_target(kind: str, folder: Path) -> Path:
    target = folder / f"{kind}.out"
    if kind == "fifo":
        os.mkfifo(target)
    elif kind == "link":
        (folder / "elsewhere.json").write_text("{}")
        target.symlink_to(folder / "elsewhere.json")
    elif kind == "directory":
        target.mkdir()
    else:
        target = folder / "no-such-folder" / "out.json"
    return target


DESK = Path(__file__).resolve().parents[1] / "svelive" / "data" / "desk.exr"


def svelive(*args: object, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "svelive.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=120, cwd=cwd)


def refused_in_one_line(out: subprocess.CompletedProcess, target: Path) -> None:
    assert out.returncode == 2, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and str(target) in lines[0] and "absent" not in lines[0], out.stderr


@pytest.fixture(scope="module")
def frame(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("frame")
    assert svelive("simulate", DESK, "--pattern", "1,4/16,64", "-o", "raw.png", cwd=folder).returncode == 0
    return folder / "raw.png"


@pytest.mark.parametrize("kind", ["fifo", "link", "directory", "missing folder"])
def test_calibrate_response_refuses_a_bad_output_before_its_fits(kind, frame, tmp_path):
    target = bad_target(kind, tmp_path)
    out = svelive("calibrate", "response", frame, "--pattern", "1,4/16,64", "--white-level", "4095", "-o", target,
                  cwd=tmp_path)
    refused_in_one_line(out, target)


@pytest.mark.parametrize("verb, kind", [(["reconstruct", "absent.png", "--pattern", "1,4/16,64"], "fifo"),
                                        (["simulate", "absent.exr", "--pattern", "1,4/16,64"], "directory")])
def test_a_bad_output_is_refused_before_the_input_is_read(verb, kind, tmp_path):
    target = bad_target(kind, tmp_path)
    refused_in_one_line(svelive(*verb, "-o", target, cwd=tmp_path), target)
