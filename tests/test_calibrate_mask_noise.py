"""Flat-field mask and noise-model calibration on simulated data with known parameters."""

import numpy as np
import pytest

from svelive import Pattern, Sensor, SveliveError, reconstruct, simulate
from svelive.calibrate import calibrate_noise, estimate_mask, load_mask, save_mask
from svelive.cli import main
from svelive.metrics import log_psnr
from svelive.simulation import exposure_scale, load_sample_scene

PATTERN = Pattern.parse("1,4/16,64")


def true_mask(n: int, seed: int = 5) -> np.ndarray:
    """Nominal tile times 3% per-pixel transmittance spread times 30% radial vignetting, float32 (n, n)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:n, 0:n]
    r2 = ((yy - n / 2) ** 2 + (xx - n / 2) ** 2) / (n / 2) ** 2
    return (PATTERN.exposure_map((n, n)) * (1 + 0.03 * rng.standard_normal((n, n))) * (1 - 0.3 * r2)).astype(np.float32)


def flats_for(mask: np.ndarray, sensor: Sensor, per_level: int) -> list[np.ndarray]:
    pattern = Pattern(PATTERN.tile, mask)
    frames = []
    for i, e in enumerate(PATTERN.levels):
        level = np.full(mask.shape, 0.8 * sensor.range_dn / e, np.float32)
        frames += [simulate(level, pattern, sensor, seed=100 * i + j).raw for j in range(per_level)]
    return frames


def test_mask_recovered_within_one_percent():
    sensor = Sensor.from_full_well(12, 40000, 5)
    truth = true_mask(96)
    est = estimate_mask(flats_for(truth, sensor, 20), (2, 2), sensor)
    ratio = est.pixel_map / truth
    ratio /= np.median(ratio)
    assert np.max(np.abs(ratio - 1)) < 0.01
    np.testing.assert_allclose(est.tile_exposures, [[1, 4], [16, 64]], rtol=0.01)
    assert est.vignetting.max() == pytest.approx(1.0)
    # the corner falls to 1 - 0.3 * 2 = 0.4 of the centre
    assert est.vignetting[0, 0] / est.vignetting[48, 48] == pytest.approx(0.4, abs=0.03)


def test_mask_improves_reconstruction():
    sensor = Sensor.from_full_well(12, 40000, 5)
    n = 128
    truth = true_mask(n, seed=7)
    est = estimate_mask(flats_for(truth, sensor, 8), (2, 2), sensor)
    scene = load_sample_scene("desk")[:n, :n]
    radiance = scene * exposure_scale(scene, PATTERN, sensor, stops_below_fill=1)
    frame = simulate(radiance, Pattern(PATTERN.tile, truth), sensor, seed=9)
    nominal = reconstruct(frame.raw, PATTERN, gain=sensor.gain, read_noise=sensor.read_noise)
    mapped = reconstruct(frame.raw, PATTERN.with_pixel_map(est.pixel_map), gain=sensor.gain,
                         read_noise=sensor.read_noise)
    assert log_psnr(mapped, frame.truth) > log_psnr(nominal, frame.truth) + 2.0


def test_mask_bad_input(tmp_path):
    sensor = Sensor(bits=12)
    saturated = np.full((64, 64), 4095, np.uint16)
    with pytest.raises(SveliveError, match="saturated"):
        estimate_mask([saturated], (2, 2), sensor)
    with pytest.raises(SveliveError, match="too dark"):
        estimate_mask([np.zeros((64, 64), np.uint16)], (2, 2), sensor)
    flats = flats_for(true_mask(64), Sensor.from_full_well(12, 10000, 3), 2)
    with pytest.raises(SveliveError, match="do not repeat with a 3x3 tile"):
        estimate_mask(flats, (3, 3), sensor)
    with pytest.raises(SveliveError, match="does not fit"):
        estimate_mask(flats, (40, 40), sensor)


def test_mask_save_load_and_cli(tmp_path, capsys):
    sensor = Sensor.from_full_well(12, 10000, 3)
    truth = true_mask(64)
    flats = flats_for(truth, sensor, 2)
    paths = []
    for i, f in enumerate(flats):
        paths.append(str(tmp_path / f"flat{i}.npy"))
        np.save(paths[-1], f)
    out = tmp_path / "mask.npz"
    assert main(["calibrate", "mask", *paths, "--tile", "2x2", "--bits", "12", "-o", str(out)]) == 0
    pixel_map = load_mask(out)
    direct = estimate_mask(flats, (2, 2), sensor)
    np.testing.assert_allclose(pixel_map, direct.pixel_map, rtol=1e-6)
    assert Pattern.parse("1,4/16,64").with_pixel_map(pixel_map).exposure_map((64, 64)).shape == (64, 64)
    assert main(["calibrate", "mask", paths[0], "--tile", "2by2", "-o", str(tmp_path / "x.npz")]) == 2
    assert "HxW" in capsys.readouterr().err
    (tmp_path / "bad.npz").write_bytes(b"junk")
    with pytest.raises(SveliveError, match="not a readable mask"):
        load_mask(tmp_path / "bad.npz")
    save_mask(direct, tmp_path / "again.npz")
    assert np.array_equal(load_mask(tmp_path / "again.npz"), direct.pixel_map)


@pytest.mark.parametrize("gain_e,read_e", [(10000, 6), (4000, 10)])
def test_noise_from_flat_pair_within_ten_percent(gain_e, read_e):
    sensor = Sensor.from_full_well(12, gain_e, read_e)
    flat = np.full((256, 256), 0.9 * sensor.range_dn / 64, np.float32)
    a = simulate(flat, PATTERN, sensor, seed=1).raw
    b = simulate(flat, PATTERN, sensor, seed=2).raw
    model = calibrate_noise([a, b], Sensor(bits=12))
    assert model.gain == pytest.approx(sensor.gain, rel=0.1)
    assert model.read_noise == pytest.approx(sensor.read_noise, rel=0.1)


def test_noise_from_one_smooth_frame_within_ten_percent():
    sensor = Sensor.from_full_well(12, 10000, 8, black_level=64)
    n = 384
    yy, xx = np.mgrid[0:n, 0:n] / n
    scene = (2.0 ** (-9 * xx) * (1 + 0.3 * np.sin(2 * np.pi * yy))).astype(np.float32)
    raw = simulate(scene * exposure_scale(scene, PATTERN, sensor), PATTERN, sensor, seed=3).raw
    model = calibrate_noise([raw], Sensor(bits=12, black_level=64), PATTERN)
    assert model.gain == pytest.approx(sensor.gain, rel=0.1)
    assert model.read_noise == pytest.approx(sensor.read_noise, rel=0.1)


DIM_BLACK0_HIGH_READ = pytest.mark.xfail(
    strict=True, reason="known limit: dim frame, 5.4 DN read noise, black level 0: few pixels clear the "
                        "4-sigma margin from raw 0, and over three noise draws the gain reads -25 % to +5 % off "
                        "and the read noise -38 % to +10 % (docs/noise.md)")


@pytest.mark.parametrize("black,full_well,read_e,stops", [
    (black, fw, re, stops) if (black, fw, re, stops) != (0, 3_000, 4, 5)
    else pytest.param(black, fw, re, stops, marks=DIM_BLACK0_HIGH_READ)
    for black in (0, 64) for fw, re in ((10_000, 3), (3_000, 4), (40_000, 6)) for stops in (0, 5)])
def test_noise_from_a_scene_pair_at_several_truths(black, full_well, read_e, stops):
    """Two frames of a real scene (texture cancels in the difference), three noise draws each. With a
    black level of 0 the dark pixels clip at raw 0; dropping the readings that hit 0 truncated their
    noise and the older estimate gave 0.0-0.98 DN read noise for a truth of 1.23 DN (10 000 e-, 3 e-)."""
    sensor = Sensor.from_full_well(12, full_well, read_e, black_level=black)
    scene = load_sample_scene("desk")
    radiance = scene * exposure_scale(scene, PATTERN, sensor, stops_below_fill=stops)
    for seeds in ((1, 2), (3, 4), (5, 6)):
        a, b = (simulate(radiance, PATTERN, sensor, seed=seed).raw for seed in seeds)
        model = calibrate_noise([a, b], Sensor(bits=12, black_level=black))
        assert model.gain == pytest.approx(sensor.gain, rel=0.15), seeds
        assert model.read_noise == pytest.approx(sensor.read_noise, rel=0.15), seeds
        assert model.read_noise_sigma is not None and model.gain_sigma is not None


def test_noise_bad_input():
    sensor = Sensor(bits=12)
    flat = np.full((64, 64), 1000, np.uint16)
    with pytest.raises(SveliveError, match="single frame needs the exposure pattern"):
        calibrate_noise([flat], sensor)
    with pytest.raises(SveliveError, match="differ in size"):
        calibrate_noise([flat, flat[:32]], sensor)
    with pytest.raises(SveliveError, match="saturated"):
        calibrate_noise([flat * 5, flat * 5], sensor)


def test_calibrate_noise_from_one_textured_frame_uses_the_reconstructions_estimator():
    # a real crop's texture: the residual line alone read this frame's gain 2.3x too high; the
    # texture-cancelled fit that svelive.reconstruct uses gets it within 15 %
    from svelive.core.camera import Camera
    from svelive.noise import estimate_from_frame as library_estimate
    from svelive.simulation import load_sample_scene

    pattern = "1,4/16,64"
    sensor = Sensor.from_full_well(12, 10_000, 3, black_level=64)
    scene = load_sample_scene("mttamwest")
    raw = simulate(scene * exposure_scale(scene, Pattern.parse(pattern), sensor), pattern, sensor, seed=1).raw
    told = Sensor(bits=12, black_level=64)
    model = calibrate_noise([raw], told, pattern)
    assert model.method == "single-frame"
    assert model.gain == pytest.approx(sensor.gain, rel=0.15)
    assert model.gain == pytest.approx(library_estimate(raw, Camera(Pattern.parse(pattern), None, told)).gain, rel=0.02)
