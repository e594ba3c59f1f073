"""Saturated colour's channels from their own lattices (svelive.reconstruction.colour.lattice), a default
stage of the joint colour path: fine detail of a saturated colour survives (dark lines on a red ground,
as the rings of the shared BrightRings image), each pixel keeps its own channel, censored pixels and
scenes without saturated colour are left as the cells make them, and CFAs that are not a 2x2 Bayer tile
are untouched. Bounds come from the same frames reconstructed without the stage (``lattice=False``)."""

from __future__ import annotations

import numpy as np
import pytest

from svelive.bench.stability import BENCH_SENSOR, CAMERA_WHITE, _simulated_rgb
from svelive.core.camera import Camera
from svelive.reconstruction.colour import joint
from svelive.reconstruction.colour.lattice import F_HIGH, flagged_cells
from svelive.reconstruction.input import prepare
from svelive.reconstruction.methods import METHODS

SHAPE = (96, 128)


def _full(layout: str) -> float:
    """Radiance (DN at exposure 1) that fills the shortest exposure of ``layout``."""
    return BENCH_SENSOR.censor_level / float(Camera.build(layout, sensor=BENCH_SENSOR).require_pattern().levels[0])


def _red_lines(layout: str, stops: float) -> np.ndarray:
    """A saturated red ground (green and blue at 0.1 % of red) with dark lines (2 % of it) four pixels wide
    every eight, slanted (so that they cross every CFA phase and line pair), ``stops`` below the short
    exposure's full scale; float32 (H, W, 3)."""
    rows, cols = np.mgrid[:SHAPE[0], :SHAPE[1]].astype(np.float32)
    lines = ((cols + 0.35 * rows) % 8.0) < 4.0
    red = np.where(lines, 0.02, 1.0).astype(np.float32) * np.float32(_full(layout) * 2.0 ** -stops)
    return np.stack([red, 1e-3 * red, 1e-3 * red], axis=-1)


def _both(truth: np.ndarray, layout: str, seed: int = 5):
    inp = prepare(_simulated_rgb(truth, layout, seed), Camera.build(layout, sensor=BENCH_SENSOR))
    spec = METHODS["adaptive"]
    return inp, joint(inp, spec, lattice=False).estimate, joint(inp, spec).estimate


def _red_error(image: np.ndarray, truth: np.ndarray, channels: np.ndarray) -> float:
    """Median |log2| error (stops) of red where the pixel reads green or blue."""
    other = channels != 0
    return float(np.median(np.abs(np.log2(np.maximum(image[..., 0][other], 1e-3) / truth[..., 0][other]))))


@pytest.mark.parametrize("layout", ["dual-iso", "column-bayer"])
@pytest.mark.parametrize("stops", [1.0, 5.0])
def test_fine_lines_of_a_saturated_colour_survive(layout, stops):
    """Dark lines on a red ground: the green and blue pixels read nothing, so the folded luminance there
    is the mono method's interpolation, which smears the lines; from the red sites' own lattice they
    stay sharper (the BrightRings rings: +2 dB PU21 over all channels on the shared frames). Red's error
    at the green and blue pixels: at most 0.8 of the cells' (0.44 -> 0.24 stop, 0.76 -> 0.43, 1.16 ->
    0.81, 1.52 -> 1.04 here)."""
    truth = _red_lines(layout, stops)
    inp, cells, lattice = _both(truth, layout)
    before, after = _red_error(cells.image, truth, inp.channels), _red_error(lattice.image, truth, inp.channels)
    assert after < 0.8 * before, (before, after)


def test_each_pixel_keeps_its_own_channel_and_censored_pixels_are_left():
    """Only the two channels a pixel does not read change, nowhere within a pixel of a censored reading;
    the luminance is sum_c n_c RGB_c where a pixel changed."""
    truth = _red_lines("dual-iso", 1.0)
    truth[:, 60:70] *= 64  # a clipped band
    inp, cells, lattice = _both(truth, "dual-iso")
    own = inp.channels[..., None].astype(np.intp)
    np.testing.assert_array_equal(np.take_along_axis(lattice.image, own, 2), np.take_along_axis(cells.image, own, 2))
    assert inp.censored.any()
    near = np.zeros_like(inp.censored)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            near |= np.roll(inp.censored, (dy, dx), axis=(0, 1))
    np.testing.assert_array_equal(lattice.image[near], cells.image[near])
    changed = np.any(lattice.image != cells.image, axis=2)
    assert changed.any()
    share = np.array([0.25, 0.5, 0.25], np.float32)
    np.testing.assert_allclose(lattice.luminance[changed], lattice.image[changed] @ share, rtol=1e-5)


@pytest.mark.parametrize("layout", ["dual-iso", "quad-bayer"])
def test_unsaturated_colour_and_other_cfas_are_left_alone(layout):
    """A grey ground with a pale colour patch (every channel's share well above F_HIGH of the largest):
    bit-identical with and without the stage; a CFA that is not a 2x2 Bayer tile (quad-Bayer) is left
    alone even on the red lines."""
    grey = np.broadcast_to(CAMERA_WHITE / CAMERA_WHITE.max() * np.float32(_full(layout) / 8), (*SHAPE, 3)).copy()
    grey[30:60, 40:90] *= np.array([1.3, 1.0, 0.8], np.float32)
    _, cells, lattice = _both(grey.astype(np.float32), layout)
    np.testing.assert_array_equal(lattice.image, cells.image)
    if layout == "quad-bayer":
        _, cells, lattice = _both(_red_lines(layout, 1.0), layout)
        np.testing.assert_array_equal(lattice.image, cells.image)


def test_flagged_cells_cover_every_pixel_the_shares_allow():
    """A pixel's shares are bilinear means of its four cells'; where none of them is flagged, every
    channel's share is at least F_HIGH times the largest (the stage's cell test skips nothing it needs)."""
    rng = np.random.default_rng(0)
    shares = rng.uniform(0.05, 2.0, (3, 12, 16)).astype(np.float32)
    flags = flagged_cells(shares)
    for _ in range(2000):
        i, j = rng.integers(0, 11), rng.integers(0, 15)
        fy, fx = rng.uniform(0, 1, 2)
        k = ((1 - fy) * (1 - fx) * shares[:, i, j] + (1 - fy) * fx * shares[:, i, j + 1]
             + fy * (1 - fx) * shares[:, i + 1, j] + fy * fx * shares[:, i + 1, j + 1])
        if k.min() < F_HIGH * k.max():
            assert flags[i:i + 2, j:j + 2].any()
