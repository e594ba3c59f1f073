import numpy as np
import pytest

from svelive import Pattern, Sensor, simulate
from svelive.simulation import exposure_scale, load_sample_scene


def test_seeded_and_typed():
    s = Sensor.from_full_well(12, 10_000, 3, black_level=64)
    radiance = np.full((16, 16), 50.0, np.float32)
    a, b = simulate(radiance, "1,4/16,64", s, seed=3), simulate(radiance, "1,4/16,64", s, seed=3)
    assert a.raw.dtype == np.uint16 and np.array_equal(a.raw, b.raw)
    assert not np.array_equal(a.raw, simulate(radiance, "1,4/16,64", s, seed=4).raw)
    assert simulate(radiance, "1,4", Sensor(8), seed=0).raw.dtype == np.uint8


def test_noise_statistics_follow_the_model():
    s = Sensor.from_full_well(12, 10_000, 3, black_level=64)
    frame = simulate(np.full((200, 200), 100.0, np.float32), "1,4/16,64", s, seed=0)
    exposure = Pattern.parse("1,4/16,64").exposure_map(frame.raw.shape)
    for e in (1, 4, 16):
        values = frame.raw[exposure == e].astype(np.float64) - 64
        assert values.mean() == pytest.approx(100 * e, rel=0.01)
        assert values.var() == pytest.approx(s.signal_variance(100 * e), rel=0.1)
    assert np.all(frame.raw[exposure == 64] == 4095)  # 6400 DN saturates


def test_scale_fills_lowest_exposure():
    scene = np.maximum(load_sample_scene("desk"), 0)
    s = Sensor(12)
    p = Pattern.parse("1,4/16,64")
    k = exposure_scale(scene, p, s)
    assert np.percentile(scene * k, 99.9) == pytest.approx(4095, rel=1e-4)
    assert exposure_scale(scene, p, s, stops_below_fill=5) == pytest.approx(k / 32)
