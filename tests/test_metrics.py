"""Accuracy metrics: PU21 on luminance and per channel, the fixed sRGB rendering, CIEDE2000."""

import sys

import numpy as np
import pytest

from svelive.core.errors import SveliveError
from svelive.metrics import (
    colour_error,
    delta_e_2000,
    display_scale,
    luminance,
    pu21_psnr,
    pu21_psnr_colour,
    render_exposure,
    render_srgb,
    srgb_to_lab,
)

# Sharma, Wu and Dalal, "The CIEDE2000 color-difference formula: implementation notes, supplementary
# test data, and mathematical observations", Color Res. Appl. 30 (2005), Table 1: L1 a1 b1 L2 a2 b2 dE00.
SHARMA_2005 = [
    (50.0000, 2.6772, -79.7751, 50.0000, 0.0000, -82.7485, 2.0425),
    (50.0000, 3.1571, -77.2803, 50.0000, 0.0000, -82.7485, 2.8615),
    (50.0000, 2.8361, -74.0200, 50.0000, 0.0000, -82.7485, 3.4412),
    (50.0000, -1.3802, -84.2814, 50.0000, 0.0000, -82.7485, 1.0000),
    (50.0000, -1.1848, -84.8006, 50.0000, 0.0000, -82.7485, 1.0000),
    (50.0000, -0.9009, -85.5211, 50.0000, 0.0000, -82.7485, 1.0000),
    (50.0000, 0.0000, 0.0000, 50.0000, -1.0000, 2.0000, 2.3669),
    (50.0000, -1.0000, 2.0000, 50.0000, 0.0000, 0.0000, 2.3669),
    (50.0000, 2.4900, -0.0010, 50.0000, -2.4900, 0.0009, 7.1792),
    (50.0000, 2.4900, -0.0010, 50.0000, -2.4900, 0.0010, 7.1792),
    (50.0000, 2.4900, -0.0010, 50.0000, -2.4900, 0.0011, 7.2195),
    (50.0000, 2.4900, -0.0010, 50.0000, -2.4900, 0.0012, 7.2195),
    (50.0000, -0.0010, 2.4900, 50.0000, 0.0009, -2.4900, 4.8045),
    (50.0000, -0.0010, 2.4900, 50.0000, 0.0010, -2.4900, 4.8045),
    (50.0000, -0.0010, 2.4900, 50.0000, 0.0011, -2.4900, 4.7461),
    (50.0000, 2.5000, 0.0000, 50.0000, 0.0000, -2.5000, 4.3065),
    (50.0000, 2.5000, 0.0000, 73.0000, 25.0000, -18.0000, 27.1492),
    (50.0000, 2.5000, 0.0000, 61.0000, -5.0000, 29.0000, 22.8977),
    (50.0000, 2.5000, 0.0000, 56.0000, -27.0000, -3.0000, 31.9030),
    (50.0000, 2.5000, 0.0000, 58.0000, 24.0000, 15.0000, 19.4535),
    (50.0000, 2.5000, 0.0000, 50.0000, 3.1736, 0.5854, 1.0000),
    (50.0000, 2.5000, 0.0000, 50.0000, 3.2972, 0.0000, 1.0000),
    (50.0000, 2.5000, 0.0000, 50.0000, 1.8634, 0.5757, 1.0000),
    (50.0000, 2.5000, 0.0000, 50.0000, 3.2592, 0.3350, 1.0000),
    (60.2574, -34.0099, 36.2677, 60.4626, -34.1751, 39.4387, 1.2644),
    (63.0109, -31.0961, -5.8663, 62.8187, -29.7946, -4.0864, 1.2630),
    (61.2901, 3.7196, -5.3901, 61.4292, 2.2480, -4.9620, 1.8731),
    (35.0831, -44.1164, 3.7933, 35.0232, -40.0716, 1.5901, 1.8645),
    (22.7233, 20.0904, -46.6940, 23.0331, 14.9730, -42.5619, 2.0373),
    (36.4612, 47.8580, 18.3852, 36.2715, 50.5065, 21.2231, 1.4146),
    (90.8027, -2.0831, 1.4410, 91.1528, -1.6435, 0.0447, 1.4441),
    (90.9257, -0.5406, -0.9208, 88.6381, -0.8985, -0.7239, 1.5381),
    (6.7747, -0.2908, -2.4247, 5.8714, -0.0985, -2.2286, 0.6377),
    (2.0776, 0.0795, -1.1350, 0.9033, -0.0636, -0.5514, 0.9082),
]


def _scene(seed=0, shape=(48, 64)):
    """A smooth HDR colour scene over ~8 stops, float32 (H, W, 3)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float32)
    base = 2.0 ** (8 * x / shape[1]) * (1 + 0.3 * np.sin(y / 5))
    tint = rng.uniform(0.3, 1.0, (1, 1, 3)).astype(np.float32)
    return (base[..., None] * tint * (1 + 0.2 * rng.random((*shape, 3)))).astype(np.float32)


def test_luminance_is_rec709_luma():
    rgb = np.zeros((1, 4, 3), np.float32)
    rgb[0, 0, 0] = rgb[0, 1, 1] = rgb[0, 2, 2] = 1.0
    rgb[0, 3] = 5.0
    np.testing.assert_allclose(luminance(rgb)[0], [0.2126, 0.7152, 0.0722, 5.0], rtol=1e-6)
    assert luminance(rgb).dtype == np.float32


def test_pu21_psnr_default_scale_is_the_references_own():
    ref = _scene()[..., 1]
    test = ref * 1.05
    assert pu21_psnr(test, ref) == pu21_psnr(test, ref, scale=display_scale(ref))
    assert pu21_psnr(test, ref, scale=10 * display_scale(ref)) != pu21_psnr(test, ref)


def test_pu21_colour_identical_images_and_a_one_channel_error():
    ref = _scene()
    same = pu21_psnr_colour(ref.copy(), ref)
    assert set(same) == {"Y", "R", "G", "B"} and all(v == float("inf") for v in same.values())
    test = ref.copy()
    test[..., 2] *= 1.2  # blue 20% high
    scores = pu21_psnr_colour(test, ref)
    assert scores["R"] == scores["G"] == float("inf")
    assert np.isfinite(scores["B"])
    # luminance holds blue at weight 0.07: its error is far smaller than the blue channel's
    assert scores["Y"] > scores["B"] + 10


def test_pu21_colour_judges_channels_at_the_luminance_scale():
    # the same relative error in a dim and a bright channel: the dim channel sits lower on the
    # PU21 curve (it is not rescaled to its own peak), where the encoding is less sensitive
    ref = _scene()
    ref[..., 0] *= 0.05
    ref[..., 2] *= 2.0
    scores = pu21_psnr_colour(ref * 1.1, ref)
    assert scores["R"] > scores["B"]


def test_pu21_colour_is_scale_invariant():
    ref = _scene()
    test = ref * np.float32(1.03) + np.float32(0.5)
    a, b = pu21_psnr_colour(test, ref), pu21_psnr_colour(test * 64, ref * 64)
    for k in a:
        assert a[k] == pytest.approx(b[k], abs=1e-6)


def test_colour_metrics_refuse_mono_and_mismatched_images():
    ref = _scene()
    with pytest.raises(SveliveError, match=r"\(H, W, 3\)"):
        pu21_psnr_colour(ref[..., 0], ref[..., 0])
    with pytest.raises(SveliveError, match="differ in shape"):
        pu21_psnr_colour(ref[:-1], ref)
    with pytest.raises(SveliveError, match=r"\(H, W, 3\)"):
        colour_error(ref, ref[..., 1])


def test_render_exposure_maps_the_log_average_to_the_key():
    grey = np.full((8, 8, 3), 4.0, np.float32)
    assert render_exposure(grey) == pytest.approx(0.18 / 4.0)
    half = grey.copy()
    half[:4] = 16.0  # log-average of 4 and 16 is 8
    assert render_exposure(half) == pytest.approx(0.18 / 8.0)
    black = grey.copy()
    black[0, 0] = 0.0  # counts at the floor 1e-4 * p99.9, not at log(0)
    assert np.isfinite(render_exposure(black)) and render_exposure(black) > render_exposure(grey)


def test_render_is_reinhard_then_srgb():
    rgb = np.array([[[0.0, 1.0, 1e6]]], np.float32)
    out = render_srgb(rgb, 1.0)
    # x/(1+x): 0 -> 0, 1 -> 0.5 (sRGB 0.7354), huge -> 1
    np.testing.assert_allclose(out[0, 0], [0.0, 1.055 * 0.5 ** (1 / 2.4) - 0.055, 1.0], atol=1e-6)


def test_lab_of_known_srgb_colours():
    pytest.importorskip("skimage")
    srgb = np.array([[[1.0, 1.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]])
    np.testing.assert_allclose(srgb_to_lab(srgb)[0], [[100.0, 0.0, 0.0], [53.2408, 80.0925, 67.2032],
                                                      [0.0, 0.0, 0.0]], atol=1e-2)


def test_ciede2000_matches_sharma_2005_reference_pairs():
    pytest.importorskip("skimage")
    data = np.array(SHARMA_2005)
    de = delta_e_2000(data[:, 0:3], data[:, 3:6])
    np.testing.assert_allclose(de, data[:, 6], atol=1e-4)
    # symmetric in its arguments
    np.testing.assert_allclose(delta_e_2000(data[:, 3:6], data[:, 0:3]), data[:, 6], atol=1e-4)


def test_colour_error_zero_for_equal_images_and_grows_with_a_hue_shift():
    pytest.importorskip("skimage")
    ref = _scene()
    assert colour_error(ref.copy(), ref) == {"de2000_mean": 0.0, "de2000_p99": 0.0}
    small, large = ref.copy(), ref.copy()
    small[..., 1] *= 0.95  # green deficit: towards magenta
    large[..., 1] *= 0.8
    e_small, e_large = colour_error(small, ref), colour_error(large, ref)
    assert 0 < e_small["de2000_mean"] < e_large["de2000_mean"]
    assert e_large["de2000_p99"] >= e_large["de2000_mean"]
    # the exposure comes from the truth: scaling both leaves the error unchanged
    scaled = colour_error(large * 100, ref * 100)
    assert scaled["de2000_mean"] == pytest.approx(e_large["de2000_mean"], rel=1e-6)


def test_colour_error_without_scikit_image_is_a_one_line_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "skimage", None)  # import skimage raises ImportError
    ref = _scene()
    with pytest.raises(SveliveError) as info:
        colour_error(ref, ref)
    message = str(info.value)
    assert "\n" not in message and "scikit-image" in message and "pip install" in message
