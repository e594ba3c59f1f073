"""Colour SVE: simulation through a colour filter, joint and split reconstruction (issue 11, section 3).

Scenes are the shipped 256x256 RGB crops (cropped further for speed) or synthetic.
"""

from __future__ import annotations

import numpy as np
import pytest

from svelive import Pattern, Sensor, SveliveError, simulate
from svelive.camera import COLOUR_LAYOUTS
from svelive.cfa import PRESETS, ColourFilter
from svelive.simulate import SAMPLE_SCENES, exposure_scale, load_sample_scene

SENSOR = Sensor.from_full_well(12, 10_000, 3)


# ----- simulation -----------------------------------------------------------------

def test_rgb_sample_scenes_load_and_match_their_luminance():
    for name in SAMPLE_SCENES:
        rgb = load_sample_scene(name, rgb=True)
        assert rgb.shape == (256, 256, 3) and rgb.dtype == np.float32
        luma = rgb @ np.array([0.2126, 0.7152, 0.0722], np.float32)
        np.testing.assert_allclose(luma, load_sample_scene(name), rtol=1e-5, atol=1e-6)


def test_exposure_scale_fills_the_shortest_exposure_with_the_brightest_channel():
    rgb = np.maximum(load_sample_scene("desk", rgb=True), 0)
    pattern = Pattern.parse("1/1/8/8")
    k = exposure_scale(rgb, pattern, SENSOR)
    assert np.percentile((rgb * k).max(axis=2), 99.9) == pytest.approx(SENSOR.range_dn, rel=1e-4)
    assert exposure_scale(rgb, pattern, SENSOR, stops_below_fill=5) == pytest.approx(k / 32)


@pytest.mark.parametrize("cfa", list(PRESETS))
def test_each_pixel_sees_its_own_channel_through_its_exposure(cfa):
    rgb = np.empty((16, 24, 3), np.float32)
    rgb[...] = (100.0, 300.0, 700.0)  # one value per channel tells the channel from the reading
    sensor = Sensor(12, gain=1e6, read_noise=0.0)  # (almost) noise-free
    frame = simulate(rgb, "1,2", sensor, cfa=cfa, seed=0)
    assert frame.truth.shape == (16, 24, 3) and frame.truth.dtype == np.float32
    np.testing.assert_array_equal(frame.truth, rgb)
    exposure = Pattern.parse("1,2").exposure_map((16, 24))
    channels = ColourFilter.parse(cfa).channel_map((16, 24))
    expected = np.array([100.0, 300.0, 700.0])[channels] * exposure
    np.testing.assert_array_equal(frame.raw, np.rint(expected).astype(np.uint16))


def test_colour_noise_follows_the_mono_model():
    rgb = np.empty((200, 200, 3), np.float32)
    rgb[...] = (40.0, 100.0, 60.0)
    frame = simulate(rgb, "1/1/8/8", SENSOR, cfa="RGGB", seed=1)
    exposure = Pattern.parse("1/1/8/8").exposure_map((200, 200))
    channels = ColourFilter.parse("RGGB").channel_map((200, 200))
    for c, level in enumerate((40.0, 100.0, 60.0)):
        for e in (1, 8):
            values = frame.raw[(channels == c) & (exposure == e)].astype(np.float64)
            assert values.mean() == pytest.approx(level * e, rel=0.01)
            assert values.var() == pytest.approx(SENSOR.signal_variance(level * e), rel=0.1)


def test_mono_simulation_ignores_nothing_it_did_before():
    radiance = np.full((16, 16), 50.0, np.float32)
    assert simulate(radiance, "1,4/16,64", SENSOR, seed=3).truth.shape == (16, 16)


@pytest.mark.parametrize("shape, cfa, message", [
    ((8, 8, 3), None, "colour filter"),  # RGB radiance without a colour filter
    ((8, 8), "RGGB", "RGB"),  # luminance with a colour filter
    ((8, 8, 4), "RGGB", "RGB"),
])
def test_mismatched_radiance_and_colour_filter_are_refused_in_one_line(shape, cfa, message):
    with pytest.raises(SveliveError) as error:
        simulate(np.ones(shape, np.float32), "1,4/16,64", SENSOR, cfa=cfa)
    assert message in str(error.value) and "\n" not in str(error.value)


@pytest.mark.parametrize("layout", list(COLOUR_LAYOUTS))
def test_every_colour_layout_simulates(layout):
    pattern, cfa = COLOUR_LAYOUTS[layout]
    rgb = np.maximum(load_sample_scene("cannon", rgb=True), 0)[:64, :64]
    frame = simulate(rgb * np.float32(exposure_scale(rgb, Pattern.parse(pattern), SENSOR)), pattern, SENSOR,
                     cfa=cfa, seed=2)
    assert frame.raw.shape == (64, 64) and frame.truth.shape == (64, 64, 3)
