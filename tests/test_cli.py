"""The svelive command: core verbs and their one-line errors (run as a real subprocess)."""

import subprocess
import sys

import cv2
import numpy as np
import pytest

from svelive.exr import read_exr


def svelive(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "svelive.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=120)


def test_info_prints_paper_figures():
    out = svelive("info", "--pattern", "nayar-r4", "--bits", "8")
    assert out.returncode == 0
    assert "84.25 dB" in out.stdout and "832" in out.stdout and "869" in out.stdout


def test_methods_lists_default():
    out = svelive("methods")
    assert out.returncode == 0 and out.stdout.splitlines()[0].endswith("(default)")


def test_demo_writes_exr_and_prints_range(tmp_path):
    out = svelive("demo", "-o", tmp_path / "demo.exr")
    assert out.returncode == 0, out.stderr
    assert "stops" in out.stdout
    channels, header = read_exr(tmp_path / "demo.exr")
    assert {"Y", "confidence"} <= set(channels) and header["pattern"] == "1,4/16,64"


@pytest.fixture
def raw_png(tmp_path):
    from svelive.simulate import sample_scene_path

    path = tmp_path / "raw.png"
    out = svelive("simulate", sample_scene_path("cannon"), "--pattern", "1,4/16,64", "--black-level", "64",
                  "-o", path, "--truth", tmp_path / "truth.exr")
    assert out.returncode == 0, out.stderr
    return path


def test_simulate_then_reconstruct(raw_png, tmp_path):
    out = svelive("reconstruct", raw_png, "--pattern", "1,4/16,64", "--black-level", "64", "--white-level", "4095",
                  "--confidence", "-o", tmp_path / "hdr.exr")
    assert out.returncode == 0, out.stderr
    channels, header = read_exr(tmp_path / "hdr.exr")
    truth, _ = read_exr(tmp_path / "truth.exr")
    assert header["method"] == "adaptive" and header["blackLevel"] == 64 and header["whiteLevel"] == 4095
    ratio = np.median(channels["Y"] / np.maximum(truth["Y"], 1e-6))
    assert ratio == pytest.approx(1.0, abs=0.02)
    assert channels["confidence"].min() >= 0 and channels["confidence"].max() <= 1


def _write(path, array):
    if path.suffix == ".npy":
        np.save(path, array)
    else:
        assert cv2.imwrite(str(path), array)
    return path


@pytest.mark.parametrize("make, words", [
    (lambda d: d / "missing.png", "no such file"),
    (lambda d: (d / "junk.png").write_bytes(b"junk") and d / "junk.png", "not a readable PNG"),
    (lambda d: _write(d / "colour.png", np.zeros((8, 8, 3), np.uint8)), "single-channel"),
    (lambda d: _write(d / "float.npy", np.zeros((8, 8), np.float32)), "8- or 16-bit"),
    (lambda d: _write(d / "float.tiff", np.zeros((8, 8), np.float32)), "8- or 16-bit"),
    (lambda d: _write(d / "tiny.png", np.zeros((1, 1), np.uint16)), "smaller than the 2x2 tile"),
    (lambda d: d, "not a file"),
])
def test_reconstruct_bad_input(tmp_path, make, words):
    source = make(tmp_path)
    out_path = tmp_path / "out.exr"
    out = svelive("reconstruct", source, "--pattern", "1,4/16,64", "-o", out_path)
    assert out.returncode == 2
    assert words in out.stderr and len(out.stderr.strip().splitlines()) == 1, out.stderr
    assert "Traceback" not in out.stderr
    assert not out_path.exists()


@pytest.mark.parametrize("args, words", [
    (["--pattern", "1,4/16"], "different lengths"),
    (["--pattern", "1,0"], "must be > 0"),
    (["--pattern", "1,4/16,64", "--black-level", "5000", "--white-level", "4095"], "below the white level"),
])
def test_reconstruct_bad_options(raw_png, tmp_path, args, words):
    out = svelive("reconstruct", raw_png, *args, "-o", tmp_path / "out.exr")
    assert out.returncode == 2 and words in out.stderr and "Traceback" not in out.stderr
    assert not (tmp_path / "out.exr").exists()
