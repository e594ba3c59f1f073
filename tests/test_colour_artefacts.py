"""Issue 27's colour artefacts, measured with the stability suite's cases (svelive.bench.stability):
small saturated lights, dark specks in dim colour regions, the line-pair staircase on slanted edges,
and the luminance/chroma EXR conversion the colour benchmark reads StarField with. Each bound comes
from the case itself (white against orange; the split baseline or the monochrome pass measured in
the same test), not from a figure of the implementation. The issue's targets that the default does
not meet yet are strict xfails: they must fail, and come off once fixed."""

from __future__ import annotations

import numpy as np
import pytest

import svelive
from svelive.bench.colour import REC709, rgb_from_luminance_chroma
from svelive.bench.stability import (
    BENCH_SENSOR,
    CAMERA_WHITE,
    _simulated_rgb,
    chromaticity_error,
    coloured_lights,
    dark_region,
    edge_positions,
    light_errors,
    periodic_amplitude,
    speck_fraction,
    stair_axis,
    staircase_amplitude,
    staircase_scene,
)
from svelive.core.camera import COLOUR_LAYOUTS, Camera
from svelive.reconstruction.input import prepare
from svelive.reconstruction.single import run_method
from svelive.simulation import simulate


def _run(truth: np.ndarray, layout: str, mode: str, seed: int = 11) -> np.ndarray:
    inp = prepare(_simulated_rgb(truth, layout, seed), Camera.build(layout, sensor=BENCH_SENSOR))
    return run_method(inp, "adaptive", colour=mode).image


def _light_errors(layout: str, level: float = -1.0) -> tuple[float, float, float]:
    """Mean over the phases of the lights' chromaticity error: joint, split, and a white light's."""
    truth, corners = coloured_lights(layout, level)
    white = np.broadcast_to(CAMERA_WHITE, truth.shape)
    return (light_errors(_run(truth, layout, "joint"), truth, corners).mean(),
            light_errors(_run(truth, layout, "split"), truth, corners).mean(),
            light_errors(white, truth, corners).mean())


@pytest.mark.parametrize("layout", ["dual-iso", "column-bayer"])
def test_small_saturated_lights_no_whiter_than_split(layout):
    """3x3 orange lights on black at every phase of the layout, bright enough to clip the long
    exposure: the mean over the phases of each light's median (r, b) chromaticity error is below the
    split baseline's (0.46 against 0.52 on dual-ISO)."""
    joint, split, _ = _light_errors(layout)
    assert joint < split, (joint, split)


@pytest.mark.parametrize("layout", ["dual-iso", "column-bayer"])
@pytest.mark.parametrize("level", [-2.0, -1.0])
def test_small_clipped_lights_no_worse_than_white(layout, level):
    """The same lights clipping the long exposure (1 and 2 stops below the short one's full scale):
    their chromaticity error is below a white light's (0.43), not violet. The cells' smoothing used
    to weigh each channel by its own unclipped share, so the light's blue (measured where red and
    green clip) spread into the black cells around and the median carried it back (dual-ISO 0.46 at
    -1 stop, 0.43 at -2, no better than white)."""
    joint, _, white = _light_errors(layout, level)
    assert joint < white, (joint, white)


@pytest.mark.parametrize("layout", ["dual-iso", "column-bayer", "quad-bayer"])
def test_small_saturated_lights_read_as_their_colour_not_white(layout):
    """The same lights: their chromaticity error is well below what a white light would score (at
    most three quarters of it: 0.32). Each light's colour is pooled from every site it lights
    (svelive.reconstruction.colour.lights): dual-ISO 0.053, column-Bayer 0.053, quad-Bayer 0.049; before, each
    cell's colour of the few sites it saw, 0.405, 0.404, 0.378 (two of eight phases orange on dual-ISO, the
    others blue, green or red). Assorted-4x4 (four exposures on a 4x4 CFA: a 3x3 light sees one or two sites of
    a channel at the exposures that do not clip) goes 0.522 -> 0.351, above this bound: test_colour_lights.py
    holds it to beating the cells."""
    joint, _, white = _light_errors(layout)
    assert joint < 0.75 * white, (joint, white)


def test_chromaticity_error_measures_colour_alone():
    """A brightness error has no chromaticity error; white for orange is about 0.4."""
    orange = np.array([1.0, 0.45, 0.08], np.float32) * CAMERA_WHITE
    assert chromaticity_error(orange * 7.5, orange) == pytest.approx(0.0, abs=1e-6)
    assert 0.35 < chromaticity_error(CAMERA_WHITE, orange) < 0.5


@pytest.mark.parametrize("layout", ["dual-iso", "assorted-4x4"])
def test_a_dim_flat_region_has_no_dark_specks(layout):
    """A flat grey region at a quarter of the long exposure's read noise beside bright lights: the
    share of its sites reading 2 stops or more below their neighbourhood in some channel is at
    most a tenth of the split baseline's (which has 3.5-4.5 %; the joint default about 0.1 %)."""
    truth, far = dark_region(layout, 0.25)
    joint = speck_fraction(_run(truth, layout, "joint"), far)
    split = speck_fraction(_run(truth, layout, "split"), far)
    assert split > 1.0, split  # the case shows specks where they are made
    assert joint <= 0.1 * split, (joint, split)


def test_speck_fraction_counts_sites_far_below_their_neighbourhood():
    flat = np.full((40, 40, 3), 10.0, np.float32)
    mask = np.ones((40, 40), bool)
    assert speck_fraction(flat, mask) == 0.0
    flat[20, 20, 2] = 1.0  # one channel 3.3 stops down
    assert speck_fraction(flat, mask) == pytest.approx(100.0 / 1600)


def test_staircase_measure_sees_a_period_of_the_pattern():
    """The periodic component of an edge position: a shift of the positions by a sine of the
    pattern's period is measured at its amplitude, a constant shift not at all."""
    position = np.linspace(0, 16, 257)[:-1]
    wave = 0.3 * np.sin(2 * np.pi * position / 4)
    assert periodic_amplitude(wave, position, 4) == pytest.approx(0.3, rel=0.02)
    assert periodic_amplitude(np.full_like(position, 0.7), position, 4) == pytest.approx(0.0, abs=1e-9)
    step = np.repeat(np.array([[1.0], [4.0]]), [5, 5], axis=0) * np.ones((1, 3))
    assert edge_positions(step, 1.0, 4.0) == pytest.approx(np.full(3, 4.5))


@pytest.mark.parametrize("contrast", [2.0, 4.0])
def test_line_pair_staircase_no_worse_than_split(contrast):
    """An edge at 3 degrees to dual-ISO's line pairs: the edge position's component at the pair
    period (4 rows) is below the split baseline's (HDR per CFA phase, then demosaicing) on the
    same frame: 0.08 against 0.12 px at 2 stops, 0.11 against 0.14 at 4."""
    truth, position, low, high = staircase_scene("dual-iso", contrast)
    joint = staircase_amplitude(_run(truth, "dual-iso", "joint"), "dual-iso", truth, position, low, high)
    split = staircase_amplitude(_run(truth, "dual-iso", "split"), "dual-iso", truth, position, low, high)
    assert joint < split, (joint, split)


@pytest.mark.xfail(strict=True, reason="known (issue 27.3): at 2 stops the colour pass staircases at the line-pair "
                   "period more than the monochrome pass on the same luminance (0.036 against 0.013 px); it follows "
                   "the mono method on the folded frame, not the chroma")
def test_line_pair_staircase_as_low_as_the_monochrome_pass():
    """At 2 stops the joint default's staircase is within 0.02 px of the monochrome pass on the
    truth's luminance with the same exposure pattern (0.036 against 0.013 px on this frame, 2026-11-29;
    0.08 against 0.02 before the pixel's own residual counted as evidence, 26c6d2d). At 4 and 5 stops the
    joint pass is below the monochrome one (0.12 / 0.17 against 0.17 / 0.33 px, mean of seeds 0-2), whose
    long rows clip on the bright side."""
    truth, position, low, high = staircase_scene("dual-iso", 2.0)
    joint = staircase_amplitude(_run(truth, "dual-iso", "joint"), "dual-iso", truth, position, low, high)
    weights = CAMERA_WHITE / float(np.sum(CAMERA_WHITE * CAMERA_WHITE))
    luminance = truth @ weights
    pattern = COLOUR_LAYOUTS["dual-iso"][0]
    raw = simulate(luminance, pattern, BENCH_SENSOR, seed=11).raw
    mono = svelive.reconstruct(raw, pattern, white_level=BENCH_SENSOR.white_level, gain=BENCH_SENSOR.gain,
                               read_noise=BENCH_SENSOR.read_noise)
    mono_rgb = mono[..., None] * CAMERA_WHITE
    assert stair_axis("dual-iso") == (0, 4)
    mono_amplitude = staircase_amplitude(mono_rgb, "dual-iso", truth, position, low, high)
    assert joint <= mono_amplitude + 0.02, (joint, mono_amplitude)


def test_luminance_chroma_exr_planes_convert_back_to_rgb():
    """Y, RY = (R - Y) / Y, BY = (B - Y) / Y (OpenEXR's luminance/chroma form) give R, G, B back:
    exactly at full size, and a smooth image within 1 % from half-size chroma."""
    yy, xx = np.mgrid[0:32, 0:48].astype(np.float32)
    rgb = np.stack([1 + xx / 48, 2 + 0 * xx, 1.5 + yy / 32], axis=-1).astype(np.float32)
    y = rgb @ np.array(REC709, np.float32)
    ry, by = rgb[..., 0] / y - 1, rgb[..., 2] / y - 1
    assert np.allclose(rgb_from_luminance_chroma(y, ry, by), rgb, rtol=1e-5)
    import cv2

    half = [cv2.resize(p, (24, 16), interpolation=cv2.INTER_AREA) for p in (ry, by)]
    back = rgb_from_luminance_chroma(y, *half)
    assert np.allclose(back[2:-2, 2:-2], rgb[2:-2, 2:-2], rtol=0.01)
