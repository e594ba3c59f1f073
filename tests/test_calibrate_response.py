"""Response calibration from one SVE frame: known curves recovered, degree chosen, bad input refused."""

import json

import numpy as np
import pytest

from svelive import Pattern, Sensor, SveliveError
from svelive.calibrate import (CURVES, Response, ResponseFitConfig, calibrate_frame, fit_response, linearise,
                               load_response, save_response, simulate_nonlinear)
from svelive.calibrate.response import SWEEP_KNOTS, common_ratio
from svelive.cli import main
from svelive.simulation import exposure_scale, load_sample_scene

PATTERN = Pattern.parse("1,4/16,64")


def chart_scene(n: int = 256, patch: int = 16, stops: float = 10.0, seed: int = 0) -> np.ndarray:
    """A calibration chart: flat patches of log-uniform radiance over ``stops`` stops, mild shading."""
    rng = np.random.default_rng(seed)
    k = n // patch
    img = np.kron(2.0 ** rng.uniform(-stops, 0, (k, k)), np.ones((patch, patch)))
    yy, xx = np.mgrid[0:n, 0:n] / n
    return (img * (1 - 0.2 * ((xx - 0.5) ** 2 + (yy - 0.5) ** 2))).astype(np.float32)


def max_error(response: Response, curve) -> float:
    lo, hi = response.stats["measured_range"]
    m = np.linspace(lo, hi, 1000)
    return float(np.max(np.abs(response(m) - curve.inverse(m))))


@pytest.mark.parametrize("bits", [12, 8])
@pytest.mark.parametrize("name", ["linear", "gamma2.2", "poly3", "s-curve"])
def test_known_curve_recovered_on_chart(name, bits):
    sensor = Sensor.from_full_well(bits, 10000, 3)
    scene = chart_scene()
    scene *= sensor.range_dn / scene.max()
    raw = simulate_nonlinear(scene, PATTERN, sensor, CURVES[name], seed=1)
    response = fit_response(raw, PATTERN, sensor)
    lo, hi = response.stats["measured_range"]
    assert hi - lo > 0.9
    assert max_error(response, CURVES[name]) < 0.02
    if name == "linear":
        assert response.degree == 1
    if name == "poly3":
        assert response.degree == 3


@pytest.mark.parametrize("scene_name", ["desk", "cannon"])
@pytest.mark.parametrize("name,degree", [("linear", 1), ("poly3", 3)])
def test_degree_on_sample_scenes(scene_name, name, degree):
    sensor = Sensor.from_full_well(12, 10000, 3)
    scene = load_sample_scene(scene_name)
    raw = simulate_nonlinear(scene * exposure_scale(scene, PATTERN, sensor), PATTERN, sensor, CURVES[name], seed=2)
    response = fit_response(raw, PATTERN, sensor)
    assert response.degree == degree
    assert max_error(response, CURVES[name]) < 0.02


def test_gamma_on_sample_scene_within_two_percent():
    sensor = Sensor.from_full_well(12, 10000, 3)
    scene = load_sample_scene("desk")
    raw = simulate_nonlinear(scene * exposure_scale(scene, PATTERN, sensor), PATTERN, sensor,
                             CURVES["gamma2.2"], seed=3)
    assert max_error(fit_response(raw, PATTERN, sensor), CURVES["gamma2.2"]) < 0.02


def test_linearise_restores_linear_frame_and_reconstruction():
    from svelive import reconstruct
    from svelive.metrics import log_psnr

    sensor = Sensor.from_full_well(12, 10000, 3)
    scene = load_sample_scene("mttamwest")
    radiance = scene * exposure_scale(scene, PATTERN, sensor, stops_below_fill=1)
    raw = simulate_nonlinear(radiance, PATTERN, sensor, CURVES["gamma2.2"], seed=4)
    response = fit_response(raw, PATTERN, sensor)
    linear = linearise(raw, response, sensor)
    assert linear.dtype == np.float32 and linear.shape == raw.shape
    assert np.all(linear[raw >= sensor.white_level] == sensor.white_level)
    plain = reconstruct(raw, PATTERN, white_level=sensor.white_level)
    fixed = reconstruct(linear, PATTERN, white_level=sensor.white_level)
    assert log_psnr(fixed, radiance) > log_psnr(plain, radiance) + 6.0


def test_linearise_float_matches_integer_path():
    response = Response((0.0, 0.2, 0.8), white_level=4095.0)
    raw = np.arange(0, 4096, 7, dtype=np.uint16).reshape(1, -1)
    a = linearise(raw, response)
    b = linearise(raw.astype(np.float32), response)
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-3)
    m = raw[0].astype(np.float64) / 4095
    np.testing.assert_allclose(a[0], 4095 * (0.2 * m + 0.8 * m * m), rtol=1e-5, atol=1e-3)


def test_save_load_roundtrip_and_bad_file(tmp_path):
    response = Response((0.01, 0.5, 0.49), (0.0, 1.0), 64.0, 4095.0, {"locations": 3})
    path = save_response(response, tmp_path / "r.json")
    back = load_response(path)
    assert back.coefficients == response.coefficients and back.black_level == 64.0
    data = json.loads(path.read_text())
    assert data["degree"] == 2 and data["coefficients"][0] == 0.01 and data["domain"] == [0.0, 1.0]
    (tmp_path / "bad.json").write_text('{"coefficients": [0, 1]}')
    with pytest.raises(SveliveError, match="white_level"):
        load_response(tmp_path / "bad.json")
    (tmp_path / "junk.json").write_text("not json")
    with pytest.raises(SveliveError, match="not a response JSON"):
        load_response(tmp_path / "junk.json")


def test_featureless_or_narrow_frames_refused():
    sensor = Sensor(bits=12)
    rng = np.random.default_rng(0)
    noise = rng.integers(0, 4096, (128, 128)).astype(np.uint16)
    with pytest.raises(SveliveError, match="not an SVE frame"):
        fit_response(noise, PATTERN, sensor)
    bright = chart_scene(128, 16, stops=1.0) * 3000 + 1100  # every exposure but the lowest saturates
    raw = simulate_nonlinear(bright, PATTERN, Sensor.from_full_well(12, 10000, 3), CURVES["linear"], seed=0)
    with pytest.raises(SveliveError, match="locally constant regions"):
        fit_response(raw, PATTERN, sensor)
    flat = np.full((128, 128), 5.0, np.float32)  # readings 5..320 DN: 8% of full scale
    raw = simulate_nonlinear(flat, PATTERN, Sensor.from_full_well(12, 10000, 3), CURVES["linear"], seed=0)
    with pytest.raises(SveliveError, match="brightness"):
        fit_response(raw, PATTERN, sensor)
    with pytest.raises(SveliveError, match="two or more"):
        fit_response(raw, Pattern.parse("1"), sensor)



def chart_frame(curve: str, seed: int) -> tuple[Sensor, np.ndarray, np.ndarray]:
    """A 12-bit sensor, a 128x128 grey chart filling its range (DN) and its raw frame through a known curve."""
    sensor = Sensor.from_full_well(12, 10000, 3)
    scene = chart_scene(128, 16)
    scene *= sensor.range_dn / scene.max()
    return sensor, scene, simulate_nonlinear(scene, PATTERN, sensor, CURVES[curve], seed=seed)


def test_calibrate_frame_for_service():
    sensor, _, raw = chart_frame("poly3", seed=5)
    data = calibrate_frame(raw, PATTERN, sensor, points=33)
    assert data["degree"] == 3
    curve = data["curve"]
    assert len(curve["brightness"]) == 33 and np.all(np.diff(curve["linear"]) >= 0)
    json.dumps(data)


def test_cli_response(tmp_path, capsys):
    sensor, _, raw = chart_frame("gamma2.2", seed=6)
    np.save(tmp_path / "raw.npy", raw)
    out = tmp_path / "response.json"
    assert main(["calibrate", "response", str(tmp_path / "raw.npy"), "--pattern", "1,4/16,64", "--bits", "12",
                 "-o", str(out)]) == 0
    assert max_error(load_response(out), CURVES["gamma2.2"]) < 0.02
    assert json.loads(out.read_text())["stats"]["common_ratio"] == 4
    assert "power of 4" in capsys.readouterr().err
    np.save(tmp_path / "noise.npy", np.random.default_rng(0).integers(0, 4096, (64, 64)).astype(np.uint16))
    assert main(["calibrate", "response", str(tmp_path / "noise.npy"), "--pattern", "1,4/16,64", "--bits", "12",
                 "-o", str(tmp_path / "n.json")]) == 2
    assert "error:" in capsys.readouterr().err
    assert not (tmp_path / "n.json").exists()


@pytest.mark.parametrize("levels, ratio", [([1, 4, 16, 64], 4), ([8, 1, 2, 4], 2), ([1, 8], 8), ([1, 4, 8], 2),
                                           ([1, 1.5, 2.25], 1.5), ([1, 3, 10, 64], None), ([1, 2, 3], None),
                                           ([5], None)])
def test_common_ratio(levels, ratio):
    """The log-periodic ambiguity exists exactly when every exposure ratio is a power of one number."""
    assert common_ratio(np.array(levels, float)) == ratio


def test_cli_reconstruct_with_response(tmp_path):
    from svelive.exr import read_exr

    sensor, scene, raw = chart_frame("gamma2.2", seed=7)
    np.save(tmp_path / "raw.npy", raw)
    resp = tmp_path / "r.json"
    save_response(fit_response(raw, PATTERN, sensor), resp)
    args = ["reconstruct", str(tmp_path / "raw.npy"), "--pattern", "1,4/16,64", "--bits", "12"]
    assert main(args + ["-o", str(tmp_path / "plain.exr")]) == 0
    assert main(args + ["--response", str(resp), "-o", str(tmp_path / "lin.exr")]) == 0
    plain = read_exr(tmp_path / "plain.exr")[0]["Y"]
    lin = read_exr(tmp_path / "lin.exr")[0]["Y"]
    err = [float(np.median(np.abs(np.log2(np.maximum(img, 1e-3) / np.maximum(scene, 1e-3))))) for img in (plain, lin)]
    assert err[1] < 0.1 < err[0]


S_CURVE_FAILS = {"desk": 0.038, "mttamwest": 0.035, "cannon": 0.035}


def _sample_case(scene_name: str, name: str):
    marks = []
    if name == "s-curve":
        marks.append(pytest.mark.xfail(strict=True, reason=(
            f"S-curve on the {scene_name} crop: max error {S_CURVE_FAILS[scene_name]:.1%} on the measured range "
            "(exposures 1, 4, 16, 64 fix f only up to f p(log_4 f), p periodic; the polynomial's misfit at the toe "
            "bends the curve along that direction, 3% even on noise-free equations; see docs/calibration.md)")))
    return pytest.param(scene_name, name, marks=marks)


@pytest.mark.parametrize("scene_name,name", [_sample_case(s, n) for s in ("desk", "mttamwest", "cannon")
                                             for n in ("linear", "gamma2.2", "poly3", "s-curve")])
def test_known_curve_recovered_on_sample_scenes(scene_name, name):
    """Real photographs: within 2% of full scale on the range the fit reports as measured."""
    sensor = Sensor.from_full_well(12, 10000, 3)
    scene = load_sample_scene(scene_name)
    raw = simulate_nonlinear(scene * exposure_scale(scene, PATTERN, sensor), PATTERN, sensor, CURVES[name], seed=2)
    response = fit_response(raw, PATTERN, sensor)
    lo, hi = response.stats["measured_range"]
    assert hi - lo >= 0.45
    assert response.stats["curve_uncertainty"] <= 0.01
    assert max_error(response, CURVES[name]) < 0.02


# ----- several frames at different global exposure times (issue 14) ---------------------------------

def sweep_frames(scene: np.ndarray, sensor: Sensor, curve: str, times=(1.0, 1.5), seed: int = 2) -> list[np.ndarray]:
    """Raw frames of ``scene`` (DN at exposure 1) at the global exposure times ``times``."""
    return [simulate_nonlinear(scene * t, PATTERN, sensor, CURVES[curve], seed=seed + i) for i, t in enumerate(times)]


@pytest.mark.parametrize("bits", [12, 8])
@pytest.mark.parametrize("name", ["linear", "gamma2.2", "poly3", "s-curve"])
def test_two_frames_on_chart_recovered_without_the_ambiguity(name, bits):
    sensor = Sensor.from_full_well(bits, 10000, 3)
    scene = chart_scene()
    scene *= sensor.range_dn / scene.max()
    response = fit_response(sweep_frames(scene, sensor, name), PATTERN, sensor, exposure_times=[10, 15])
    stats = response.stats
    assert stats["frames"] == 2 and stats["exposure_times"] == [10, 15]
    assert stats["nominal_exposures"] == [1, 4, 16, 64, 1.5, 6, 24, 96]
    assert stats["common_ratio"] is None  # 1.5 is no power of the pattern's 4
    lo, hi = stats["measured_range"]
    assert hi - lo > 0.9
    assert max_error(response, CURVES[name]) < 0.02
    if name == "linear":
        assert response.degree == 1


def test_sweep_uses_between_frame_equations_and_gives_a_band():
    sensor = Sensor.from_full_well(12, 10000, 3)
    scene = chart_scene(128, 16)
    scene *= sensor.range_dn / scene.max()
    frames = sweep_frames(scene, sensor, "gamma2.2", times=(1.0, 1.5, 2.25))
    one = fit_response(frames[0], PATTERN, sensor)
    three = fit_response(frames, PATTERN, sensor, exposure_times=[2, 3, 4.5])
    # within each frame 6 level pairs, between every two frames 16: 3 * 6 + 3 * 16 per location at most
    assert three.stats["equations"] > 4 * one.stats["equations"]
    band = three.stats["band"]
    lo, hi = three.stats["measured_range"]
    m = np.asarray(band["brightness"])
    assert m[0] == lo and m[-1] == hi and len(m) == 33
    np.testing.assert_allclose(band["linear"], three(m), atol=1e-12)
    se = np.asarray(band["standard_error"])
    assert np.all(se > 0) and se.max() < 0.01
    assert max(one.stats["band"]["standard_error"]) > se.max()  # more frames, narrower band


def test_sweep_input_refused_with_the_fix():
    sensor = Sensor.from_full_well(12, 10000, 3)
    scene = chart_scene(128, 16)
    scene *= sensor.range_dn / scene.max()
    a, b = sweep_frames(scene, sensor, "linear")
    with pytest.raises(SveliveError, match="exposure times"):
        fit_response([a, b], PATTERN, sensor)
    with pytest.raises(SveliveError, match="one per frame"):
        fit_response([a, b], PATTERN, sensor, exposure_times=[1, 2, 3])
    with pytest.raises(SveliveError, match="positive"):
        fit_response([a, b], PATTERN, sensor, exposure_times=[1, 0])
    with pytest.raises(SveliveError, match="one camera and region"):
        fit_response([a, b[:64]], PATTERN, sensor, exposure_times=[1, 1.5])
    # the times in the wrong order: the brighter frame reads darker everywhere
    with pytest.raises(SveliveError, match="order of the exposure times"):
        fit_response([a, b], PATTERN, sensor, exposure_times=[1.5, 1])


def saved_chart_sweep(tmp_path, curve: str) -> list[str]:
    """Two 12-bit frames of the chart through ``curve`` at exposures 1 and 1.5, saved as .npy; their paths."""
    sensor = Sensor.from_full_well(12, 10000, 3)
    scene = chart_scene()
    scene *= sensor.range_dn / scene.max()
    paths = []
    for i, raw in enumerate(sweep_frames(scene, sensor, curve)):
        np.save(tmp_path / f"f{i}.npy", raw)
        paths.append(str(tmp_path / f"f{i}.npy"))
    return paths


def test_cli_sweep_progress_quiet_and_bits_from_the_file(tmp_path, capsys):
    frames = saved_chart_sweep(tmp_path, "gamma2.2")
    out = tmp_path / "r.json"
    # no --bits: the saturated patches hold 4095, a 12-bit white
    assert main(["calibrate", "response", *frames, "--exposure-times", "8000,12000", "--pattern", "1,4/16,64",
                 "-o", str(out)]) == 0
    err = capsys.readouterr().err
    assert "degree 1/6" in err and "frame 2/2" in err and "power of" not in err
    data = json.loads(out.read_text())
    assert data["white_level"] == 4095 and data["stats"]["exposure_times"] == [8000, 12000]
    assert max_error(load_response(out), CURVES["gamma2.2"]) < 0.02
    assert main(["calibrate", "response", *frames, "--exposure-times", "8000,12000", "--pattern", "1,4/16,64",
                 "-q", "-o", str(out)]) == 0
    assert capsys.readouterr().err == ""
    assert main(["calibrate", "response", *frames, "--pattern", "1,4/16,64", "-o", str(out)]) == 2
    assert "--exposure-times" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # argparse's own error
        main(["calibrate", "response", *frames, "--exposure-times", "1,x", "--pattern", "1,4/16,64", "-o", str(out)])
    assert "exposure times are numbers" in capsys.readouterr().err


def test_cli_bits_unknown_names_the_option(tmp_path, capsys):
    """A 16-bit file with nothing saturated and no sBIT does not say its bit depth."""
    raw = np.random.default_rng(0).integers(0, 3000, (64, 64)).astype(np.uint16)
    cv2 = pytest.importorskip("cv2")
    cv2.imwrite(str(tmp_path / "dim.png"), raw)
    for verb in (["response", "--pattern", "1,4/16,64", "-o", str(tmp_path / "r.json")],
                 ["mask", "--tile", "2x2", "-o", str(tmp_path / "m.npz")]):
        assert main(["calibrate", verb[0], str(tmp_path / "dim.png"), *verb[1:]]) == 2
        err = capsys.readouterr().err
        assert "--bits" in err and "dim.png" in err and len(err.strip().splitlines()) == 1


def test_bits_from_png_sbit_and_from_saturation(tmp_path):
    import struct
    import zlib

    from svelive.cli.calibrate import png_significant_bits, saturation_bits

    cv2 = pytest.importorskip("cv2")
    raw = np.zeros((32, 32), np.uint16)
    raw[:8] = 4095
    assert saturation_bits(raw) == 12
    raw[0, 0] = 4000  # still 12: the cluster at 4095 stays
    assert saturation_bits(raw) == 12
    assert saturation_bits(np.full((32, 32), 3000, np.uint16)) is None
    one = raw.copy()
    one[:8] = 0
    one[0, 0] = 1023  # a single pixel at 2^10 - 1 is no evidence
    assert saturation_bits(one) is None
    path = tmp_path / "f.png"
    cv2.imwrite(str(path), raw)
    assert png_significant_bits(path) is None
    data = path.read_bytes()
    chunk = b"sBIT" + bytes([12])
    sbit = struct.pack(">I", 1) + chunk + struct.pack(">I", zlib.crc32(chunk))
    (tmp_path / "s.png").write_bytes(data[:33] + sbit + data[33:])  # after the 8-byte signature and IHDR
    assert png_significant_bits(tmp_path / "s.png") == 12
    assert cv2.imread(str(tmp_path / "s.png"), cv2.IMREAD_UNCHANGED).max() == 4095


#: the S-curve cases that still fail from two frames with the default fit (the log-spline offered), and why
S_CURVE_TWO_FRAMES_FAILS = {
    "mttamwest": "2.6 % off, nearly all of it a scale error of +2 %: the data end at M = 0.957, and only about 40 "
                 "pixels of the crop lie within 5 % of white's light in the brighter frame to pin the shoulder "
                 "from there to white (4.1 % before the pixels at white entered the fit)",
    "cannon": "0.5 % off, but the measured range is 0.01-0.50 (under 0.75): the standard error passes 1 % above",
}


def _two_frame_case(scene_name: str, name: str):
    marks = []
    if name == "s-curve" and scene_name in S_CURVE_TWO_FRAMES_FAILS:
        marks.append(pytest.mark.xfail(strict=True, reason=f"S-curve on the {scene_name} crop from two frames (1 "
                                                           f"and 1.5): {S_CURVE_TWO_FRAMES_FAILS[scene_name]}"))
    return pytest.param(scene_name, name, marks=marks)


@pytest.mark.parametrize("scene_name,name", [_two_frame_case(s, n) for s in ("desk", "mttamwest", "cannon")
                                             for n in ("linear", "gamma2.2", "poly3", "s-curve")])
def test_known_curve_recovered_on_sample_scenes_from_two_frames(scene_name, name):
    """Real photographs at global exposures 1 and 1.5: within 1% of full scale on the measured range."""
    sensor = Sensor.from_full_well(12, 10000, 3)
    scene = load_sample_scene(scene_name)
    frames = sweep_frames(scene * exposure_scale(scene, PATTERN, sensor), sensor, name)
    response = fit_response(frames, PATTERN, sensor, exposure_times=[1.0, 1.5])
    lo, hi = response.stats["measured_range"]
    assert hi - lo >= 0.75
    assert response.stats["curve_uncertainty"] <= 0.01
    assert max_error(response, CURVES[name]) < 0.01


# ----- the log-spline model (sweeps without a common exposure ratio) ------------------------------

def test_log_spline_basis_is_a_natural_cubic_spline():
    from svelive.calibrate.response import log_spline_basis

    knots = np.log([0.01, 0.05, 0.2, 0.6, 1.0])
    below, above = np.linspace(-9.0, knots[0], 7), np.linspace(knots[-1], 2.0, 7)
    for u in (below, above):  # straight lines outside the knots
        np.testing.assert_allclose(np.diff(log_spline_basis(u, knots), 2, axis=0), 0.0, atol=1e-9)
    u = np.linspace(-6.0, 0.5, 301)
    step = 1e-6
    numeric = (log_spline_basis(u + step, knots) - log_spline_basis(u - step, knots)) / (2 * step)
    np.testing.assert_allclose(log_spline_basis(u, knots, derivative=True), numeric, atol=1e-6)
    assert log_spline_basis(u, knots).shape == (301, 4)


def test_log_spline_response_evaluates_round_trips_and_linearises(tmp_path):
    knots = (0.01, 0.1, 0.5, 1.0)
    # log f = 1.1 log M + small curvature, f(1) = 1
    from svelive.calibrate.response import log_spline_basis

    rest = np.array([1.1, 0.05, -0.02])
    constant = -float(log_spline_basis(np.zeros(1), np.log(knots))[0] @ rest)
    response = Response((constant, *rest), white_level=4095.0, knots=knots)
    m = np.linspace(0.0, 1.0, 2001)
    f = response(m)
    assert response.model == "log-spline" and f[0] == 0.0 and abs(f[-1] - 1.0) < 1e-12
    assert np.all(np.diff(f) > 0)
    np.testing.assert_allclose(response(np.array([0.001, 0.005])), np.array([0.001, 0.005]) ** 1.1 * np.exp(constant),
                               rtol=1e-9)  # a power law below the first knot
    step = 1e-7
    mid = m[10:-10]
    np.testing.assert_allclose(response.slope(mid), (response(mid + step) - response(mid - step)) / (2 * step),
                               rtol=1e-5, atol=1e-7)
    back = load_response(save_response(response, tmp_path / "s.json"))
    assert back == response and back.knots == knots
    data = json.loads((tmp_path / "s.json").read_text())
    assert data["model"] == "log-spline" and data["knots"] == list(knots)
    raw = np.arange(0, 4096, 5, dtype=np.uint16).reshape(1, -1)
    np.testing.assert_allclose(linearise(raw, response)[0], 4095 * response(raw[0] / 4095.0), rtol=1e-5, atol=1e-3)
    data["knots"] = [0.5, 0.1, 0.9, 1.0]
    (tmp_path / "bad.json").write_text(json.dumps(data))
    with pytest.raises(SveliveError, match="increasing knots"):
        load_response(tmp_path / "bad.json")
    assert "knots" not in Response((0.0, 1.0)).to_dict()  # polynomial files as before


def test_log_spline_offered_to_sweeps_by_default_never_to_one_frame():
    sensor = Sensor.from_full_well(12, 10000, 3)
    scene = chart_scene(128, 16)
    scene *= sensor.range_dn / scene.max()
    frames = sweep_frames(scene, sensor, "gamma2.2")
    spline = ResponseFitConfig(max_knots=6)
    one = fit_response(frames[0], PATTERN, sensor, spline)
    assert one.model == "polynomial" and all(k.isdigit() for k in one.stats["held_out_error"])
    assert all(k.isdigit() for k in fit_response(frames[0], PATTERN, sensor).stats["held_out_error"])
    default = fit_response(frames, PATTERN, sensor, exposure_times=[1, 1.5])
    assert {k for k in default.stats["held_out_error"] if not k.isdigit()} == {"log-spline 2",
                                                                                f"log-spline {SWEEP_KNOTS}"}
    polynomial = fit_response(frames, PATTERN, sensor, ResponseFitConfig(max_knots=0), exposure_times=[1, 1.5])
    assert all(k.isdigit() for k in polynomial.stats["held_out_error"])
    two = fit_response(frames, PATTERN, sensor, spline, exposure_times=[1, 1.5])
    # two sizes, the power law and max_knots, not a choice of the knot count
    assert {k for k in two.stats["held_out_error"] if k.startswith("log-spline")} == {"log-spline 2", "log-spline 6"}
    # gamma 2.2 is a power law, the log-spline's simplest form (2 knots: one free parameter)
    assert two.model == "log-spline" and len(two.knots) == 2
    # the last knot at the top of the data; above it, up to white, the power law of the last slope
    assert two.knots[-1] == two.stats["data_range"][1] < 1.0 and abs(float(two(1.0)) - 1.0) < 1e-12
    assert max_error(two, CURVES["gamma2.2"]) < min(0.005, max_error(polynomial, CURVES["gamma2.2"]))
    band = two.stats["band"]
    np.testing.assert_allclose(band["linear"], two(np.asarray(band["brightness"])), atol=1e-12)
    # 1 and 4 (powers of the pattern's 4): the ripple is invisible again, so no spline
    four = fit_response([frames[0], sweep_frames(scene / 4, sensor, "gamma2.2")[0]], PATTERN, sensor, spline,
                        exposure_times=[4, 1])
    assert four.stats["common_ratio"] == 4 and four.model == "polynomial"
    assert not any(k.startswith("log-spline") for k in four.stats["held_out_error"])


def test_the_held_out_rule_takes_the_log_spline_for_an_s_curve_sweep():
    """On the desk crop's S-curve from two frames the default fit chooses the 12-knot log-spline (the
    polynomials alone are 2.4 % off there: docs/calibration.md) and is within 1 % of full scale."""
    sensor = Sensor.from_full_well(12, 10000, 3)
    scene = load_sample_scene("desk")
    frames = sweep_frames(scene * exposure_scale(scene, PATTERN, sensor), sensor, "s-curve")
    response = fit_response(frames, PATTERN, sensor, exposure_times=[1.0, 1.5])
    assert response.model == "log-spline" and len(response.knots) == SWEEP_KNOTS
    assert max_error(response, CURVES["s-curve"]) < 0.01


def test_probit_finds_where_and_how_sharply_pixels_reach_white():
    """The probit of the pixels at white: from binomial counts drawn at a known threshold and width (sd of
    log light) both come back within a few of their sampling errors (about 0.0004 and 3 %)."""
    import math

    from svelive.calibrate.response.censored import _probit_newton

    rng = np.random.default_rng(3)
    x = np.linspace(-0.1, 0.1, 201)  # log light predicted in the brighter frame, less white's
    total = np.full(x.size, 50.0)
    threshold, width = 0.012, 0.02
    p = np.array([0.5 * math.erfc(-(v - threshold) / width / math.sqrt(2.0)) for v in x])
    hits = rng.binomial(50, p).astype(np.float64)
    rows = np.stack([np.ones_like(x), x], axis=1)
    offset, slope = _probit_newton(lambda q: rows @ q, rows, np.array([0.0, 10.0]), total, hits)
    assert abs(1.0 / slope - width) < 0.15 * width
    assert abs(-offset / slope - threshold) < 0.002


def test_pixels_at_white_counted_by_their_darker_reading():
    from svelive.calibrate.response.censored import _censored_at_white

    sensor = Sensor.from_full_well(12, 10000, 3)
    dark = np.array([[100, 3000, 3000], [4095, 0, 3000]], np.uint16)
    bright = np.array([[150, 4095, 4000], [4095, 4095, 4095]], np.uint16)
    rows = _censored_at_white([bright, dark], np.array([1.5, 1.0]), sensor)
    # readings at black or at white in the darker frame say nothing about the light at white
    np.testing.assert_allclose(rows.m, [100 / 4095, 3000 / 4095])
    assert rows.total.tolist() == [1, 3] and rows.clipped.tolist() == [0, 2] and rows.pair.tolist() == [0, 0]
    np.testing.assert_allclose(rows.log_ratio, np.log(1.5))
    assert rows.threshold == 1.0 - 0.5 / 4095  # the ADC rounds: white from half a step under it


def test_sweep_pins_the_log_spline_at_white_with_the_pixels_own_noise():
    """A sweep offered the log-spline fits it with the pixels that reach white in the brighter frame. The
    probit's width is the two readings' noise in log light near white (photon noise of 10 000 e-: about
    1.5 %), measured on the same pixels: the frame's own noise curve, which counts the crop's texture as
    noise, would make it about 10 %."""
    sensor = Sensor.from_full_well(12, 10000, 3)
    scene = load_sample_scene("desk")
    frames = sweep_frames(scene * exposure_scale(scene, PATTERN, sensor), sensor, "s-curve")
    response = fit_response(frames, PATTERN, sensor, ResponseFitConfig(max_knots=12), exposure_times=[1.0, 1.5])
    near = response.stats["pixels_near_white"]
    assert near["pixels"] > near["at_white"] > 100
    assert len(near["width"]) == 1 and 0.01 < near["width"][0] < 0.03
    polynomial = ResponseFitConfig(max_knots=0)
    assert fit_response(frames, PATTERN, sensor, polynomial, exposure_times=[1.0, 1.5]).stats["pixels_near_white"] is None


@pytest.mark.parametrize("scene_name", ["desk", "mttamwest", "cannon"])
@pytest.mark.parametrize("name,degree", [("linear", 1), ("poly3", 3)])
def test_log_spline_on_offer_keeps_polynomial_cameras_at_8_bits(scene_name, name, degree):
    """8 bits, global exposures 1 and 1.5, the log-spline offered: a dark window's rounding error is
    shared by every location of its brightness, so a flexible model that follows it wins held-out error
    unless models are compared on equations rounding barely moves (and the error weighs as the step it
    can be). The camera's own degree is then chosen, within 0.2 % of full scale."""
    sensor = Sensor.from_full_well(8, 10000, 3)
    scene = load_sample_scene(scene_name)
    frames = sweep_frames(scene * exposure_scale(scene, PATTERN, sensor), sensor, name)
    response = fit_response(frames, PATTERN, sensor, ResponseFitConfig(max_knots=12), exposure_times=[1.0, 1.5])
    assert any(key.startswith("log-spline") for key in response.stats["held_out_error"])
    assert response.model == "polynomial" and response.degree == degree
    assert max_error(response, CURVES[name]) < 0.002


def test_cli_max_knots_offers_the_log_spline_to_a_sweep(tmp_path, capsys):
    frames = saved_chart_sweep(tmp_path, "s-curve")
    args = ["calibrate", "response", *frames, "--exposure-times", "8000,12000", "--pattern", "1,4/16,64", "-q"]
    assert main([*args, "--max-knots", "0", "-o", str(tmp_path / "poly.json")]) == 0
    without = json.loads((tmp_path / "poly.json").read_text())
    assert not any(key.startswith("log-spline") for key in without["stats"]["held_out_error"])
    assert main([*args, "-o", str(tmp_path / "default.json")]) == 0
    default = json.loads((tmp_path / "default.json").read_text())
    assert sorted(k for k in default["stats"]["held_out_error"] if k.startswith("log-spline")) == \
        ["log-spline 12", "log-spline 2"]
    capsys.readouterr()
    assert main([*args, "--max-knots", "8", "-o", str(tmp_path / "spline.json")]) == 0
    line = capsys.readouterr().out
    spline = json.loads((tmp_path / "spline.json").read_text())
    offered = [key for key in spline["stats"]["held_out_error"] if key.startswith("log-spline")]
    assert sorted(offered) == ["log-spline 2", "log-spline 8"]
    # the summary names the model the held-out rule chose
    chosen = load_response(tmp_path / "spline.json")
    assert line.startswith(f"log-spline, {len(chosen.knots)} knots" if chosen.knots else f"degree {chosen.degree}")
    assert main([*args, "--max-knots", "40", "-o", str(tmp_path / "bad.json")]) == 2
    assert "max knots must be 0..16" in capsys.readouterr().err and not (tmp_path / "bad.json").exists()
