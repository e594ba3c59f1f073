import numpy as np
import pytest

from svelive import Sensor, SveliveError


def test_defaults_from_bit_depth():
    s = Sensor(bits=10)
    assert s.white_level == 1023
    assert s.range_dn == 1023


def test_full_well_gives_gain_and_read_noise_in_dn():
    s = Sensor.from_full_well(12, 10_000, 3, black_level=64)
    assert s.gain == pytest.approx(10_000 / (4095 - 64))
    assert s.read_noise == pytest.approx(3 / s.gain)
    # variance: shot noise in DN^2 plus read noise and quantisation
    assert s.signal_variance(1000.0) == pytest.approx(1000 / s.gain + s.read_noise**2 + 1 / 12)


def test_censor_level_is_below_white_by_the_noise():
    s = Sensor.from_full_well(12, 10_000, 3)
    sigma = np.sqrt(s.signal_variance(s.range_dn))
    assert s.censor_level == pytest.approx(s.range_dn - 2 * sigma)


@pytest.mark.parametrize("kwargs, words", [
    (dict(bits=0), "bit depth"),
    (dict(bits=12, black_level=5000, white_level=4095), "below the white level"),
    (dict(bits=12, black_level=100, white_level=100), "below the white level"),
    (dict(bits=12, gain=0), "gain"),
    (dict(bits=12, read_noise=-1), "read noise"),
    (dict(bits=12, black_level=-1), "black level"),
])
def test_bad_sensor_values(kwargs, words):
    with pytest.raises(SveliveError, match=words):
        Sensor(**kwargs)
