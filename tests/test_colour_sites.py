"""Chroma per site (svelive.reconstruction.colour.sites), the joint colour path's opt-in stage: small
lights keep their colour beyond what the cells hold, each pixel keeps its own channel, censored pixels
and layouts that are not a 2x2 Bayer keep the cells' chroma, and noise in a dim grey is not painted
as colour. Bounds come from the same frames reconstructed with the cells' chroma alone."""

from __future__ import annotations

import numpy as np
import pytest

from svelive.bench.stability import BENCH_SENSOR, CAMERA_WHITE, _simulated_rgb, coloured_lights, light_errors
from svelive.core.camera import Camera
from svelive.reconstruction.colour import joint
from svelive.reconstruction.colour.sites import applies
from svelive.reconstruction.input import prepare
from svelive.reconstruction.methods import METHODS


def _both(truth: np.ndarray, layout: str, seed: int = 11):
    inp = prepare(_simulated_rgb(truth, layout, seed), Camera.build(layout, sensor=BENCH_SENSOR))
    spec = METHODS["adaptive"]
    cells = joint(inp, spec, site_chroma=False).estimate
    sites = joint(inp, spec, site_chroma=True).estimate
    return inp, cells, sites


@pytest.mark.parametrize("layout", ["dual-iso", "column-bayer"])
def test_small_lights_keep_their_colour_with_chroma_per_site(layout):
    """3x3 orange lights on black at every phase, 4 stops below the short exposure's full scale
    (unclipped): the cells' chroma (4x2 cells, 3x3 smoothing and median) takes the black ground's
    around them (0.20); per site the lights' own sites give it (0.12 here): at most three quarters
    of the cells' error."""
    truth, corners = coloured_lights(layout, -4.0)
    _, cells, sites = _both(truth, layout)
    before = light_errors(cells.image, truth, corners).mean()
    after = light_errors(sites.image, truth, corners).mean()
    assert after < 0.75 * before, (after, before)


def test_each_pixel_keeps_its_own_channel_and_censored_pixels_the_cells_colour():
    """The stage changes only the two channels a pixel does not read, and nothing at a censored
    pixel (a bound, whose colour the cells' highlight rules give); the luminance is the new
    sum_c n_c RGB_c where a pixel changed."""
    truth, _ = coloured_lights("dual-iso", 0.5)  # clips the short rows too
    inp, cells, sites = _both(truth, "dual-iso")
    own = inp.channels[..., None].astype(np.intp)
    np.testing.assert_array_equal(np.take_along_axis(sites.image, own, 2), np.take_along_axis(cells.image, own, 2))
    assert inp.censored.any()
    np.testing.assert_array_equal(sites.image[inp.censored], cells.image[inp.censored])
    changed = np.any(sites.image != cells.image, axis=2)
    assert changed.any()
    share = np.array([0.25, 0.5, 0.25], np.float32)
    np.testing.assert_allclose(sites.luminance[changed], sites.image[changed] @ share, rtol=1e-5)


def test_layouts_without_a_bayer_tile_keep_the_cells_chroma():
    truth, _ = coloured_lights("quad-bayer", -4.0)
    inp, cells, sites = _both(truth, "quad-bayer")
    assert not applies(inp.cfa)
    np.testing.assert_array_equal(sites.image, cells.image)


@pytest.mark.xfail(strict=True, reason="known: on a flat grey at 3 sigma of the long rows' read noise the spread is "
                   "3.5 times the cells' (0.0054 against 0.0015): the garrote's 5x5 evidence holds about three "
                   "independent smoothed residuals, so noise passes it at about 40 % of the pixels")
def test_dim_flat_grey_is_not_painted_with_colour_noise():
    """A flat grey at the long exposure's read noise (dual-ISO): per-site ratios are far noisier
    than the cells', and the garrote keeps the cells' there: the mean (r, b) chromaticity spread is
    at most 5 % above the cells' alone."""
    level = 3.0 * float(np.sqrt(BENCH_SENSOR.floor_variance)) / 8.0
    truth = np.broadcast_to(np.float32(level) * CAMERA_WHITE, (96, 96, 3)).astype(np.float32)
    _, cells, sites = _both(truth, "dual-iso")

    def spread(rgb: np.ndarray) -> float:
        rb = rgb[..., [0, 2]] / np.maximum(rgb.sum(-1, keepdims=True), 1e-6)
        return float(np.mean(np.abs(rb - rb.reshape(-1, 2).mean(0))))

    assert spread(sites.image[4:-4, 4:-4]) <= 1.05 * spread(cells.image[4:-4, 4:-4]), (
        spread(sites.image), spread(cells.image))
