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
    assert "stops" in out.stdout and "white balance (auto)" in out.stdout
    channels, header = read_exr(tmp_path / "demo.exr")
    # in colour by default: the demo camera's dual-ISO layout on RGGB, camera RGB with its white balance
    assert set(channels) == {"R", "G", "B", "confidence"} and header["pattern"] == "1/1/8/8"
    assert header["cfa"] == "RGGB" and header["colourSpace"] == "camera" and header["whiteBalance"][1] == 1
    rgb = np.dstack([channels[c] for c in "RGB"])
    assert np.all(np.isfinite(rgb)) and rgb.min() >= 0
    assert np.abs(np.log(rgb[..., 0] + 1) - np.log(rgb[..., 2] + 1)).mean() > 0.05  # not a grey image
    out = svelive("demo", "--cfa", "none", "-o", tmp_path / "mono.exr")
    assert out.returncode == 0, out.stderr
    channels, header = read_exr(tmp_path / "mono.exr")
    assert set(channels) == {"Y", "confidence"} and header["pattern"] == "1,4/16,64" and "cfa" not in header


@pytest.fixture
def raw_png(tmp_path):
    from svelive.simulation import sample_scene_path

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


@pytest.fixture
def bayer_png(tmp_path):
    """A simulated dual-ISO RGGB raw frame of a shipped RGB crop, and its RGB truth."""
    from svelive.simulation import sample_scene_path

    path = tmp_path / "bayer.png"
    out = svelive("simulate", sample_scene_path("desk"), "--pattern", "1/1/8/8", "--cfa", "RGGB", "--black-level",
                  "64", "-o", path, "--truth", tmp_path / "truth_rgb.exr")
    assert out.returncode == 0, out.stderr
    assert "colour filter RGGB" in out.stdout
    return path


def test_simulate_and_reconstruct_in_colour(bayer_png, tmp_path):
    raw = cv2.imread(str(bayer_png), cv2.IMREAD_UNCHANGED)
    assert raw.ndim == 2  # a mosaic, one value per pixel
    truth, truth_header = read_exr(tmp_path / "truth_rgb.exr")
    assert set(truth) == {"R", "G", "B"} and truth_header["cfa"] == "RGGB"
    out = svelive("reconstruct", bayer_png, "--pattern", "1/1/8/8", "--cfa", "RGGB", "--black-level", "64",
                  "--white-level", "4095", "--confidence", "-o", tmp_path / "rgb.exr")
    assert out.returncode == 0, out.stderr
    channels, header = read_exr(tmp_path / "rgb.exr")
    assert set(channels) == {"R", "G", "B", "confidence"}
    assert header["cfa"] == "RGGB" and header["colourSpace"] == "camera" and header["whiteBalanceApplied"] == 0
    assert "chromaticities" not in header
    for c in "RGB":  # the scale of every channel: within 2 % of the truth
        assert np.median(channels[c] / np.maximum(truth[c], 1e-6)) == pytest.approx(1.0, abs=0.02), c

    # the same frame in Rec.709: white balance and matrix applied, the standard chromaticities
    matrix = [1.5, -0.3, -0.2, -0.2, 1.4, -0.2, 0.0, -0.4, 1.4]
    out = svelive("reconstruct", bayer_png, "--pattern", "dual-iso", "--black-level", "64", "--white-level", "4095",
                  "--white-balance", "2,1,1.5", "--colour-matrix", ",".join(map(str, matrix)),
                  "--output-space", "rec709", "-o", tmp_path / "rec709.exr")
    assert out.returncode == 0, out.stderr
    rec709, header = read_exr(tmp_path / "rec709.exr")
    assert header["colourSpace"] == "rec709" and header["whiteBalanceApplied"] == 1
    assert header["chromaticities"] == pytest.approx((0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290), abs=1e-6)
    camera = np.dstack([channels[c] for c in "RGB"]).astype(np.float64)
    expected = np.einsum("ij,hwj->hwi", np.reshape(matrix, (3, 3)) @ np.diag([2, 1, 1.5]), camera)
    np.testing.assert_allclose(np.dstack([rec709[c] for c in "RGB"]), expected, rtol=1e-4, atol=1e-3)


@pytest.mark.parametrize("args, words", [
    (["--cfa", "RGGX"], "'RGGX' in row 1 is not R, G or B"),
    (["--cfa", "R,G/G"], "different lengths"),
    (["--pattern", "dual-iso", "--cfa", "GRBG"], "drop --cfa"),
    (["--cfa", "RGGB", "--output-space", "rec709"], "needs a colour matrix"),
    (["--cfa", "RGGB", "--white-balance", "1,2"], "expected 3 numbers"),
])
def test_colour_refusals_are_one_line(bayer_png, tmp_path, args, words):
    base = ["--pattern", "1/1/8/8"] if "--pattern" not in args else []
    out = svelive("reconstruct", bayer_png, *base, *args, "-o", tmp_path / "out.exr")
    assert out.returncode == 2 and words in out.stderr, out.stderr
    assert len(out.stderr.strip().splitlines()) == 1 and not (tmp_path / "out.exr").exists()


def test_cfa_with_a_demosaiced_image_and_simulate_refusals(tmp_path):
    from svelive.simulation import sample_scene_path

    rgb = _write(tmp_path / "rgb.png", np.full((8, 8, 3), 100, np.uint8))
    out = svelive("reconstruct", rgb, "--pattern", "1/1/8/8", "--cfa", "RGGB", "-o", tmp_path / "out.exr")
    assert out.returncode == 2 and "3-channel (already demosaiced)" in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1
    out = svelive("simulate", sample_scene_path("desk"), "--pattern", "1/1/8/8", "--cfa", "XYZ", "-o",
                  tmp_path / "r.png")
    assert out.returncode == 2 and "is not R, G or B" in out.stderr and not (tmp_path / "r.png").exists()


def test_reconstruct_sequence_uses_the_recordings_camera_and_response(tmp_path):
    from replay import RecordingWriter
    from svelive.calibrate import fit_response
    from svelive.cli import main
    from svelive.core.camera import Camera
    from svelive.core.frame import Frame
    from tests.test_calibrate_response import PATTERN, chart_frame

    sensor, scene, first = chart_frame("gamma2.2", seed=7)
    response = fit_response(first, PATTERN, sensor)
    errors = {}
    for name, camera in (("linear", Camera.build(PATTERN, None, sensor)),
                         ("with response", Camera.build(PATTERN, None, sensor, response))):
        path = tmp_path / f"{name}.sverec"
        with RecordingWriter(path) as writer:  # a camera with a non-linear response, recorded with its camera
            for i, seed in enumerate((8, 9)):
                writer.append(Frame(raw=chart_frame("gamma2.2", seed=seed)[2], frame_id=i, host_time_ns=i * 33_000_000,
                                    pixel_format="Mono12", camera=camera))
        out = tmp_path / name
        assert main(["reconstruct-sequence", "--source", f"replay:{path}", "--speed", "0", "--no-temporal",
                     "-o", str(out)]) == 0
        channels, header = read_exr(out / "frame_000001.exr")
        assert set(channels) == {"Y", "confidence", "motion"} and header["pattern"] == str(PATTERN)
        errors[name] = float(np.median(np.abs(np.log2(np.maximum(channels["Y"], 1e-3) / np.maximum(scene, 1e-3)))))
    # the response the recording carries linearises every frame; without it the gamma curve stays
    assert errors["with response"] < 0.1 < errors["linear"], errors


@pytest.mark.parametrize("temporal", [False, True])
def test_reconstruct_sequence_of_a_bayer_recording_writes_rgb(tmp_path, temporal):
    from svelive.cli import main

    path = tmp_path / "bayer.sverec"
    assert main(["record", "--source", "demo", "--cfa", "RGGB", "--width", "96", "--height", "64", "--fps", "0",
                 "--frames", "3", "-o", str(path)]) == 0
    out = tmp_path / "exr"
    assert main(["reconstruct-sequence", "--source", f"replay:{path}", "--speed", "0", "-o", str(out)]
                + ([] if temporal else ["--no-temporal"])) == 0
    files = sorted(out.glob("*.exr"))
    assert len(files) == 3
    channels, header = read_exr(files[-1])
    assert set(channels) == {"R", "G", "B", "confidence", "motion"}
    assert header["cfa"] == "RGGB" and header["colourSpace"] == "camera" and header["whiteBalanceMode"] == "auto"
    rgb = np.dstack([channels[c] for c in "RGB"])
    assert rgb.shape == (64, 96, 3) and np.all(np.isfinite(rgb)) and rgb.min() >= 0
    assert channels["motion"].shape == (64, 96) and channels["confidence"].shape == (64, 96)


def test_reconstruct_names_the_noise_model_it_used(raw_png, tmp_path):
    out = svelive("reconstruct", raw_png, "--pattern", "1,4/16,64", "--black-level", "64", "--white-level", "4095",
                  "-v", "-o", tmp_path / "est.exr")
    assert out.returncode == 0, out.stderr
    line = out.stdout.strip().splitlines()[-1]
    assert line.startswith("noise (") and "e-/DN" in line, out.stdout
    _, header = read_exr(tmp_path / "est.exr")
    assert header["noiseSource"] in ("estimated", "default") and header["noiseGain"] > 0
    given = svelive("reconstruct", raw_png, "--pattern", "1,4/16,64", "--black-level", "64", "--white-level", "4095",
                    "--gain", "2.5", "--read-noise", "1.5", "-v", "-o", tmp_path / "given.exr")
    assert given.returncode == 0, given.stderr
    assert "noise (given): gain 2.5 e-/DN, read noise 1.5 DN" in given.stdout
    _, header = read_exr(tmp_path / "given.exr")
    assert header["noiseSource"] == "given" and header["noiseGain"] == 2.5 and header["noiseReadNoise"] == 1.5
