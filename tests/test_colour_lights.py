"""Small clipped lights take one colour pooled from every site they light (svelive.reconstruction.colour.lights);
what is not such a light keeps the cells' colour, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from svelive.bench.stability import (
    BENCH_SENSOR,
    CAMERA_WHITE,
    _simulated_rgb,
    chromaticity_error,
    coloured_lights,
    light_errors,
)
from svelive.core.camera import Camera
from svelive.reconstruction.colour import joint, light_colours
from svelive.reconstruction.input import prepare
from svelive.reconstruction.single import method_spec


def _joint(truth: np.ndarray, layout: str, lights: bool, seed: int = 11):
    inp = prepare(_simulated_rgb(truth, layout, seed), Camera.build(layout, sensor=BENCH_SENSOR))
    return inp, joint(inp, method_spec("adaptive"), lights=lights)


@pytest.mark.parametrize("layout", ["dual-iso", "column-bayer"])
def test_every_clipped_light_is_recoloured_and_its_colour_is_right(layout):
    truth, corners = coloured_lights(layout, -1.0)
    inp, off = _joint(truth, layout, lights=False)
    image, luminance = off.estimate.image.copy(), off.estimate.luminance.copy()
    assert light_colours(inp, luminance, image, off.chroma.white, off.chroma.layout) == len(corners)
    before, after = light_errors(off.estimate.image, truth, corners), light_errors(image, truth, corners)
    assert after.mean() < 0.5 * before.mean(), (after.mean(), before.mean())
    # each pixel keeps its own channel's value, and the luminance is that of its new colour
    own = inp.channels[..., None].astype(np.intp)
    assert np.array_equal(np.take_along_axis(image, own, -1), np.take_along_axis(off.estimate.image, own, -1))
    share = off.chroma.layout.share
    changed = np.any(image != off.estimate.image, axis=-1)
    assert changed.any()
    assert np.allclose(luminance[changed], image[changed] @ share, rtol=1e-5)


@pytest.mark.parametrize("level", [-6.0, -4.0])
def test_lights_that_do_not_clip_keep_the_cells_colour(level):
    """Below the long exposure's clipping the cells' colour holds the light's measured readings; the stage
    leaves the frame bit for bit."""
    truth, _ = coloured_lights("dual-iso", level)
    _, on = _joint(truth, "dual-iso", lights=True)
    _, off = _joint(truth, "dual-iso", lights=False)
    assert np.array_equal(on.estimate.image, off.estimate.image)


def test_a_small_white_light_that_clips_stays_white():
    """No magenta, no tint: a neutral 3x3 light clipping the long rows keeps a neutral colour."""
    truth, corners = coloured_lights("dual-iso", -1.0)
    lit = np.any(truth[:96] > 0, axis=-1)
    white = truth.copy()
    white[:96][lit] = CAMERA_WHITE / CAMERA_WHITE.max() * truth[:96][lit].max()
    _, on = _joint(white, "dual-iso", lights=True)
    errors = [np.median(chromaticity_error(on.estimate.image[y:y + 3, x:x + 3], white[y:y + 3, x:x + 3]))
              for y, x in corners]
    assert max(errors) < 0.05, errors


@pytest.mark.parametrize("layout", ["dual-iso", "column-bayer", "quad-bayer", "assorted-4x4"])
@pytest.mark.parametrize("level", [-2.0, -1.0])
def test_clipped_lights_come_out_closer_to_their_colour_than_the_cells_on_every_layout(layout, level):
    truth, corners = coloured_lights(layout, level)
    _, on = _joint(truth, layout, lights=True)
    _, off = _joint(truth, layout, lights=False)
    with_stage = light_errors(on.estimate.image, truth, corners)
    cells = light_errors(off.estimate.image, truth, corners)
    assert with_stage.mean() < 0.7 * cells.mean(), (with_stage.mean(), cells.mean())


@pytest.mark.parametrize("layout", ["dual-iso", "assorted-4x4"])
def test_peaked_clipped_stars_keep_the_cells_colour(layout):
    """Gaussian stars (sigma 0.8 px) whose cores clip: each channel's lit sites sit at different heights of the
    profile, so their means are not the star's colour; the readings are not flat within their noise, and the
    stage leaves them (with no flatness test it recolours 40 of these 64 stars on dual-ISO)."""
    yy, xx = np.mgrid[0:96, 0:96].astype(np.float32)
    truth = np.zeros((96, 96, 3), np.float32)
    colour = np.array([0.3, 1.0, 0.9], np.float32) * CAMERA_WHITE * BENCH_SENSOR.censor_level / 2
    for i, cy in enumerate(range(10, 90, 10)):
        for j, cx in enumerate(range(10, 90, 10)):
            r2 = (yy - cy - 0.25 * (i % 4)) ** 2 + (xx - cx - 0.5 * (j % 2)) ** 2
            truth += np.exp(-r2 / (2 * 0.8**2))[..., None] * colour
    inp, off = _joint(truth, layout, lights=False)
    assert inp.censored.sum() > 64
    image, luminance = off.estimate.image.copy(), off.estimate.luminance.copy()
    assert light_colours(inp, luminance, image, off.chroma.white, off.chroma.layout) == 0


def test_a_light_that_samples_one_channel_or_a_large_clipped_area_keeps_the_cells_colour():
    """A one-pixel light tells one channel, so its colour is unknown; a clipped area two cells wide or more is
    the cells' to colour. Neither changes."""
    truth = np.full((64, 64, 3), 2.0, np.float32) * CAMERA_WHITE
    full = BENCH_SENSOR.censor_level
    truth[22, 21] = np.array([1.0, 0.4, 0.1], np.float32) * full / 2  # a long-row pixel: it clips
    truth[36:50, 30:50] = CAMERA_WHITE * full / 2
    inp, off = _joint(truth, "dual-iso", lights=False)
    assert inp.censored[22, 21] and inp.censored[36:50, 30:50].any()
    image, luminance = off.estimate.image.copy(), off.estimate.luminance.copy()
    assert light_colours(inp, luminance, image, off.chroma.white, off.chroma.layout) == 0
    assert np.array_equal(image, off.estimate.image)
