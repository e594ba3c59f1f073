"""Motion robustness: consistency test, temporal fusion, stability cases, API and CLI of issue 5.

Scenes are the shipped 256x256 crops (cropped further for speed) or synthetic.
"""

from __future__ import annotations

import numpy as np
import pytest

import svelive
from svelive import Pattern, Sensor, SveliveError
from svelive.cli import main
from svelive.exr import read_exr
from svelive.metrics import PU21_PEAK, display_scale, pu21_encode, pu21_psnr
from svelive.motion import FrameEstimate, MotionConfig, disagree, sharpen
from svelive.reconstructor import Reconstructor, own_reading_rows, reconstruct_sequence
from svelive.scenes import mains_flicker, modulated, moving_disc, panning, render_sequence, static
from svelive.simulate import exposure_scale, load_sample_scene

PATTERN = "1,4/16,64"
SENSOR = Sensor.from_full_well(12, 10_000, 3)
KW = dict(white_level=SENSOR.white_level, gain=SENSOR.gain, read_noise=SENSOR.read_noise)


def scene_dn(name: str, stops: float, size: int = 128) -> np.ndarray:
    image = np.maximum(load_sample_scene(name), 0)[:size, :size]
    return image * np.float32(exposure_scale(image, Pattern.parse(PATTERN), SENSOR, stops_below_fill=stops))


def region_pu21(test: np.ndarray, truth: np.ndarray, region: np.ndarray) -> float:
    s = display_scale(truth)
    err = pu21_encode(test[region] * s) - pu21_encode(truth[region] * s)
    return float(10 * np.log10(PU21_PEAK**2 / np.mean(err * err)))


def fused_and_single(frames, **kw):
    # "single frame" = the same method without fusion: what fusion adds or costs
    fused = Reconstructor(PATTERN, **KW, **kw)
    single = Reconstructor(PATTERN, temporal=False, method=fused.method, **KW, **kw)
    return [(f, fused.process(f.raw), single.process(f.raw)) for f in frames]


def assert_finite(result) -> None:
    for array in (result.image, result.variance, result.confidence):
        assert np.all(np.isfinite(array))
    assert result.image.min() >= 0
    assert 0 <= result.confidence.min() and result.confidence.max() <= 1


# ----- building blocks --------------------------------------------------------

def test_disagree_is_the_noise_model_test():
    a = np.array([10, 10, 10], np.float32)
    b = np.array([10, 13, 17], np.float32)
    var = np.full(3, 0.5, np.float32)  # sqrt(0.5 + 0.5) = 1
    assert disagree(a, var, b, var, 4.0).tolist() == [False, False, True]


def test_sharpen_keeps_smooth_within_noise_and_follows_strong_detail():
    mean = np.full(4, 100, np.float32)
    own = np.array([100, 101, 200, 200], np.float32)
    threshold = np.array([9, 9, 9, np.inf], np.float32)
    out = sharpen(mean, own, threshold)
    assert out[0] == 100 and out[1] == 100  # |diff| <= 3 sigma: unchanged
    assert 199 < out[2] <= 200  # 100 sigma: the pixel's own value
    assert out[3] == 100  # infinite threshold: no history, no detail


@pytest.mark.parametrize("shape", [(7, 9), (1, 5)])
@pytest.mark.parametrize("per_pixel", [False, True])
def test_frame_rows_by_phase_give_every_pixel_its_own_reading_and_noise(shape, per_pixel):
    rng = np.random.default_rng(4)
    pattern = Pattern.parse(PATTERN)
    if per_pixel:
        calibrated = pattern.exposure_map(shape) * rng.uniform(0.9, 1.1, shape).astype(np.float32)
        pattern = pattern.with_pixel_map(calibrated)
    exposure = pattern.exposure_map(shape)
    signal = rng.uniform(0, 4095, shape).astype(np.float32)
    censored = signal > 3500
    image = rng.uniform(0, 100, shape).astype(np.float32)
    inverse, slope, floor = own_reading_rows(pattern, shape, SENSOR, 9.0)
    frame = FrameEstimate(image, image, censored, censored, signal, inverse, slope, floor)
    np.testing.assert_allclose(frame.own, np.where(censored, image, signal / exposure), rtol=1e-6)
    rows = np.arange(shape[0]) % inverse.shape[0]
    np.testing.assert_allclose(slope[rows], 9.0 / (exposure * SENSOR.effective_gain), rtol=1e-6)
    np.testing.assert_allclose(floor[rows], 9.0 * SENSOR.floor_variance / exposure**2, rtol=1e-6)


def test_config_rejects_bad_values():
    with pytest.raises(SveliveError, match="max_history"):
        MotionConfig(max_history=0)
    with pytest.raises(SveliveError, match="temporal_sigmas"):
        MotionConfig(temporal_sigmas=-1)


# ----- targets ------------------------------------------------------------------

def test_dim_static_scene_gains_3db_after_8_frames_and_motion_stays_empty():
    frames = list(render_sequence(static(scene_dn("desk", 5)), 8, PATTERN, SENSOR, seed=11))
    out = fused_and_single(frames)
    f, fused, single = out[-1]
    assert pu21_psnr(fused.image, f.truth) >= pu21_psnr(single.image, f.truth) + 3.0
    false_alarms = np.mean([r.moving_fraction for _, r, _ in out[1:]])
    assert false_alarms < 0.005
    assert fused.frames_fused.max() == 8
    assert_finite(fused)


def test_moving_disc_leaves_no_trail_and_moving_pixels_match_single_frame():
    background = scene_dn("mttamwest", 4)
    scene = moving_disc(background, float(background.max()) * 3, 12, (64, 20), (0, 10))
    out = fused_and_single(render_sequence(scene, 8, PATTERN, SENSOR, seed=2))
    moved = [f.motion for f, _, _ in out]
    for i, (f, fused, single) in enumerate(out[2:], start=2):
        previous = out[i - 1][0].truth
        doubled = np.abs(f.truth - previous) > 0.5 * (f.truth + previous)  # disc arrived or left: ratio > 3
        assert doubled.any() and np.all(fused.motion[doubled] | (fused.weight[doubled] == 1))
        assert_finite(fused)
        trail = np.any(moved[i - 2:i], axis=0) & ~f.motion
        assert region_pu21(fused.image, f.truth, trail) >= region_pu21(single.image, f.truth, trail) - 0.5
        assert region_pu21(fused.image, f.truth, f.motion) >= region_pu21(single.image, f.truth, f.motion) - 0.5


def test_integration_timing_consistency_lowers_edge_error():
    background = scene_dn("desk", 5)
    scene = moving_disc(background, float(background.max()) * 4, 14, (64, 30), (0, 12))
    frames = list(render_sequence(scene, 5, PATTERN, SENSOR, timing="integration", seed=4))
    with_test = Reconstructor(PATTERN, exposure_timing="integration", **KW)
    without = Reconstructor(PATTERN, exposure_timing="integration", consistency=False, **KW)
    assert with_test.consistency and not without.consistency
    a = [with_test.process(f.raw) for f in frames]
    b = [without.process(f.raw) for f in frames]
    for f, x, y in zip(frames[1:], a[1:], b[1:]):
        assert region_pu21(x.image, f.truth, f.motion) > region_pu21(y.image, f.truth, f.motion)
        assert pu21_psnr(x.image, f.truth) > pu21_psnr(y.image, f.truth)


# ----- stability ------------------------------------------------------------------

def test_global_illumination_jump_is_divided_out_not_reset():
    scene = modulated(static(scene_dn("desk", 3)), lambda t: 1.0 if t < 4 else 2.0)
    out = fused_and_single(render_sequence(scene, 7, PATTERN, SENSOR, seed=5))
    f, fused, single = out[4]
    assert fused.illumination_ratio == pytest.approx(2.0, rel=0.02)
    assert fused.moving_fraction < 0.01
    assert pu21_psnr(fused.image, f.truth) >= pu21_psnr(single.image, f.truth) - 0.5
    for _, fused, _ in out:
        assert_finite(fused)


def test_camera_pan_every_pixel_moves_no_worse_than_single_frame():
    image = np.maximum(load_sample_scene("mttamwest"), 0)
    image *= np.float32(exposure_scale(image, Pattern.parse(PATTERN), SENSOR, stops_below_fill=1))
    out = fused_and_single(render_sequence(panning(image, (96, 96), (0.0, 4.0), (10, 10)), 6, PATTERN, SENSOR))
    for f, fused, single in out[1:]:
        assert_finite(fused)
        assert pu21_psnr(fused.image, f.truth) >= pu21_psnr(single.image, f.truth) - 0.5
        assert fused.moving_fraction > 0.3


@pytest.mark.parametrize("mains_hz", [50.0, 60.0])
def test_mains_flicker_stays_finite_and_close_to_single_frame(mains_hz):
    scene = modulated(static(scene_dn("cannon", 3, 96)), mains_flicker(fps=30, mains_hz=mains_hz, depth=0.3))
    out = fused_and_single(render_sequence(scene, 6, PATTERN, SENSOR, duty=0.2, seed=6))
    for f, fused, single in out:
        assert_finite(fused)
        assert pu21_psnr(fused.image, f.truth) >= pu21_psnr(single.image, f.truth) - 0.5
    assert np.mean([r.moving_fraction for _, r, _ in out[1:]]) < 0.05


def test_sudden_saturation_recovers_within_one_frame():
    base = scene_dn("desk", 4, 96)
    box = np.zeros(base.shape, bool)
    box[30:60, 30:60] = True
    flash = base.copy()
    flash[box] = SENSOR.range_dn * 4  # saturates every exposure
    scene = lambda t: flash if 3 <= t < 5 else base  # noqa: E731
    out = fused_and_single(render_sequence(scene, 8, PATTERN, SENSOR, seed=8))
    for f, fused, single in out:
        assert_finite(fused)
    assert out[3][1].lower_bound[31:59, 31:59].all()
    f, fused, single = out[5]  # first frame after the change ends
    inner = np.zeros_like(box)
    inner[33:57, 33:57] = True
    assert region_pu21(fused.image, f.truth, inner) >= region_pu21(single.image, f.truth, inner) - 0.5
    assert not fused.lower_bound[inner].any()


# ----- API -----------------------------------------------------------------------

def test_method_change_restarts_history_and_bad_arguments_are_one_line_errors():
    raw = render_sequence(static(scene_dn("cannon", 2, 64)), 1, PATTERN, SENSOR)
    raw = next(raw).raw
    r = svelive.Reconstructor(PATTERN, **KW)
    r.process(raw)
    assert r.process(raw).frames_fused.max() == 2
    r.method = "aggregate"
    res = r.process(raw)
    assert res.method == "aggregate" and res.frames_fused.max() == 1
    assert r.state()["method"] == "aggregate"
    with pytest.raises(SveliveError, match="unknown method"):
        r.method = "nope"
    with pytest.raises(SveliveError, match="exposure timing"):
        Reconstructor(PATTERN, exposure_timing="global")
    assert r.process(raw[:32, :32]).frames_fused.max() == 1  # a new frame size restarts


def test_reconstruct_sequence_takes_arrays_and_frames():
    frames = list(render_sequence(static(scene_dn("cannon", 2, 64)), 3, PATTERN, SENSOR))
    items = [frames[0].raw, svelive.Frame(raw=frames[1].raw, frame_id=1, host_time_ns=0), frames[2].raw]
    results = list(reconstruct_sequence(items, PATTERN, **KW))
    assert [r.frame_index for r in results] == [0, 1, 2]
    assert results[-1].frames_fused.max() == 3


def test_cli_writes_one_exr_per_frame(tmp_path):
    frames = list(render_sequence(static(scene_dn("cannon", 2, 64)), 3, PATTERN, SENSOR))
    src = tmp_path / "raw"
    src.mkdir()
    for i, f in enumerate(frames):
        np.save(src / f"f{i}.npy", f.raw)
    out = tmp_path / "out"
    assert main(["reconstruct-sequence", "--source", str(src), "--pattern", PATTERN, "--white-level", "4095",
                 "-o", str(out)]) == 0
    files = sorted(out.glob("*.exr"))
    assert len(files) == 3
    channels, _ = read_exr(files[-1])
    assert set(channels) == {"Y", "confidence", "motion"}
    assert pu21_psnr(channels["Y"], frames[-1].truth) > 25
    assert main(["reconstruct-sequence", "--source", str(src), "-o", str(out)]) == 2  # no pattern
