"""The noise model of a stream whose camera gives no gain or read noise: estimated from its first frames
(svelive.reconstruction.stream.stream_noise) by reconstruct-sequence and by reprocessing, used for every
frame and named in every EXR, instead of the fixed defaults."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pytest

from svelive.cli import main
from svelive.core.camera import Camera
from svelive.core.frame import Frame
from svelive.core.sensor import Sensor
from svelive.exr import read_exr
from svelive.cli.motion import with_cameras
from svelive.noise import estimate_from_frame
from svelive.reconstruction.stream import NOISE_FRAMES, Reconstructor, stream_noise
from svelive.simulation import exposure_scale, load_sample_scene, simulate

PATTERN = "1,4/16,64"
#: far from the defaults (10 000 e- full well, 3 e- read noise): 40 000 e-, 6 e- (0.6 DN at 12 bits)
TRUE = Sensor.from_full_well(12, 40_000, 6, black_level=64)
UNKNOWN = Sensor(12, black_level=64)


def still_frames(name: str, n: int, sensor: Sensor = TRUE) -> list[np.ndarray]:
    """``n`` raw frames of a shipped crop, the same light, independent noise."""
    scene = np.maximum(load_sample_scene(name), 0)
    pattern = Camera.build(PATTERN, None, sensor).require_pattern()
    return [simulate(scene * exposure_scale(scene, pattern, sensor), pattern, sensor, seed=s).raw for s in range(n)]


@pytest.mark.parametrize("name", ["desk", "mttamwest", "cannon"])
def test_three_still_frames_give_the_gain_within_15_percent_where_the_defaults_are_four_times_off(name):
    camera = Camera.build(PATTERN, None, UNKNOWN)
    frames = still_frames(name, NOISE_FRAMES)
    estimate = stream_noise(frames, camera)
    assert estimate.source == "estimated"
    assert abs(estimate.gain / TRUE.gain - 1) < 0.15, estimate.describe()
    assert abs(UNKNOWN.effective_gain / TRUE.gain - 1) > 0.5  # the defaults the stream would have used
    # the stated uncertainty covers the error (two sigmas)
    assert abs(estimate.gain - TRUE.gain) < 2 * estimate.gain_sigma + 0.15 * TRUE.gain
    # one frame is what stream_noise gives for a single frame
    one = stream_noise(frames[:1], camera)
    assert (one.gain, one.read_noise) == (estimate_from_frame(frames[0], camera).gain,
                                          estimate_from_frame(frames[0], camera).read_noise)


def test_given_values_are_kept_and_no_frame_is_an_error():
    given = Camera.build(PATTERN, None, TRUE)
    estimate = stream_noise(still_frames("desk", 1), given)
    assert (estimate.gain, estimate.read_noise, estimate.source) == (TRUE.gain, TRUE.read_noise, "given")
    half = Camera.build(PATTERN, None, Sensor(12, black_level=64, gain=TRUE.gain))  # gain given, read noise not
    estimate = stream_noise(still_frames("desk", 2), half)
    assert estimate.apply(half.sensor).gain == TRUE.gain and estimate.source == "estimated"
    with pytest.raises(Exception, match="no frame"):
        stream_noise([], Camera.build(PATTERN, None, UNKNOWN))


def _args(**kw) -> argparse.Namespace:
    base = dict(pattern=PATTERN, cfa=None, black_level=64, white_level=4095, gain=None, read_noise=None,
                method=None, timing="mask")
    return argparse.Namespace(**{**base, **kw})


def test_with_cameras_estimates_once_per_camera_from_the_frames_ahead():
    first_camera = Camera.build(PATTERN, None, UNKNOWN)
    other_camera = Camera.build("1,2/4,8", None, UNKNOWN)
    other_sensor = Sensor.from_full_well(12, 20_000, 4, black_level=64)
    scene = np.maximum(load_sample_scene("mttamwest"), 0)
    pattern = other_camera.require_pattern()
    others = [simulate(scene * exposure_scale(scene, pattern, other_sensor), pattern, other_sensor, seed=s).raw
              for s in range(2)]
    frames = [Frame(raw, frame_id=i, host_time_ns=i, camera=first_camera)
              for i, raw in enumerate(still_frames("desk", 5))]
    frames += [Frame(raw, frame_id=5 + i, host_time_ns=5 + i, camera=other_camera) for i, raw in enumerate(others)]
    out = list(with_cameras(frames, _args()))
    assert [f for f, _, _ in out] == frames  # every frame, in order, once
    first, second = out[0][2], out[5][2]
    assert all(noise is first for _, _, noise in out[:5]) and all(noise is second for _, _, noise in out[5:])
    assert first.gain == stream_noise([f.raw for f in frames[:NOISE_FRAMES]], first_camera).gain
    assert second.gain == stream_noise(others, other_camera).gain  # the two frames of that camera
    assert out[0][1].sensor.gain == first.gain and out[5][1].sensor.gain == second.gain
    assert out[5][1].pattern == other_camera.pattern
    # given on the command line: nothing estimated
    given = list(with_cameras(frames[:2], _args(gain=TRUE.gain, read_noise=TRUE.read_noise)))
    assert {noise.source for _, _, noise in given} == {"given"}


def test_reconstruct_sequence_uses_and_names_the_streams_estimate(tmp_path: Path, capsys):
    frames = still_frames("cannon", 4)
    src = tmp_path / "raw"
    src.mkdir()
    for i, raw in enumerate(frames):
        np.save(src / f"f{i}.npy", raw)
    out = tmp_path / "out"
    assert main(["reconstruct-sequence", "--source", str(src), "--pattern", PATTERN, "--black-level", "64",
                 "--white-level", "4095", "--no-temporal", "-o", str(out)]) == 0
    assert "noise (estimated)" in capsys.readouterr().err
    camera = Camera.build(PATTERN, None, UNKNOWN)
    estimate = stream_noise(frames[:NOISE_FRAMES], camera, exposure_timing="mask")
    used = camera.replace(sensor=estimate.apply(UNKNOWN))
    for i, raw in enumerate(frames):
        channels, attributes = read_exr(out / f"frame_{i:06d}.exr")
        assert attributes["noiseSource"] == "estimated"
        assert attributes["noiseGain"] == pytest.approx(estimate.gain, rel=1e-6)
        np.testing.assert_array_equal(channels["Y"], Reconstructor(used, temporal=False).process(raw).image)
    defaults = Reconstructor(camera, temporal=False).process(frames[-1]).image
    assert not np.array_equal(channels["Y"], defaults)  # not the defaults' result


def test_a_frame_delivered_twice_adds_nothing_to_the_tracker():
    """A repeated buffer (a driver sending the last frame again, a short loop of recorded frames) differs from
    the one before by nothing: taken as a static pair it said the sensor had no temporal noise (the live
    service, whose test source loops eight frames, then trusted gain 3.0 / read noise 2.8 DN for 1.5 / 4.1)."""
    from svelive.noise import NoiseTracker

    camera = Camera.build(PATTERN, None, UNKNOWN)
    raws = still_frames("desk", 3)
    still = np.ones(raws[0].shape, bool)
    once, twice = NoiseTracker(), NoiseTracker()
    for i, raw in enumerate(raws):
        once.add(raw, camera, None if i == 0 else still)
        twice.add(raw, camera, None if i == 0 else still)
        twice.add(raw.copy(), camera, still)
    assert twice.fit() == once.fit()
