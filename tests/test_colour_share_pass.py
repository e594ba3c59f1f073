"""The chroma's passes over the cell rows (svelive.reconstruction.colour.shares: ``_cell_pass`` and ``_share_pass``,
or ``_chroma_pass`` with the white balance given) against the chain of whole-plane steps with OpenCV's filters
they replaced (issue 25, colour speed): bit for bit, on every colour layout, bright and dim (clipped and
noise-limited), at sizes down to a single cell row and column."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from svelive import Camera, Pattern, Sensor, simulate
from svelive.core.camera import COLOUR_LAYOUTS
from svelive.reconstruction.colour import chroma
from svelive.reconstruction.colour import shares as S
from svelive.reconstruction.colour.cells import _cell_stats, cell_layout
from svelive.reconstruction.colour.highlights import _cell_values_row, white_balance
from svelive.reconstruction.input import prepare
from svelive.reconstruction.methods.base import SveInput, binomial_kernel
from svelive.simulation import exposure_scale, load_sample_scene

SENSOR = Sensor.from_full_well(12, 10_000, 3)


def _whole_planes(inp: SveInput) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(shares, coarse, white) of ``chroma`` as it was computed before the one pass: each step over whole
    (3, Hc, Wc) planes, the smoothing, centring and median by OpenCV, the per-cell arithmetic by the
    pass's own row kernels called row by row from here."""
    f32 = np.float32
    layout = cell_layout(inp.pattern, inp.cfa)
    (cy, cx), (h, w) = layout.cell, inp.shape
    hc, wc = -(-h // cy), -(-w // cx)
    mean, info, kept, weighted, bound = (np.empty((3, hc, wc), f32) for _ in range(5))
    flags = np.empty((2, hc, wc), np.uint8)
    sensor = inp.sensor
    _cell_stats(inp.signal, inp.censored, layout.channels, layout.levels, layout.exposures, False,
                f32(1.0 / sensor.effective_gain), f32(sensor.floor_variance), f32(sensor.censor_level),
                mean, info, kept, weighted, bound, flags, np.empty((3, 3, layout.exposures.size, wc), f32),
                np.empty((6, wc), f32))
    k = binomial_kernel(3)
    spread = f32(np.sum(k * k) ** 2)
    common = kept.min(axis=0)
    products = common * mean
    numerator, denominator = np.empty((3, hc, wc), f32), np.empty((3, hc, wc), f32)
    for c in range(3):
        cv2.sepFilter2D(products[c], cv2.CV_32F, k, k, dst=numerator[c], borderType=cv2.BORDER_REFLECT_101)
    cv2.sepFilter2D(common, cv2.CV_32F, k, k, dst=denominator[0], borderType=cv2.BORDER_REFLECT_101)
    denominator[1:] = denominator[0]
    none = np.nonzero(denominator[0] <= 0)
    for c in range(3):
        numerator[c][none], denominator[c][none] = weighted[c][none], kept[c][none]
    box = np.ones((3, 3), np.uint8)
    clipped, censored = (cv2.dilate(flags[i], box, borderType=cv2.BORDER_REFLECT_101) for i in range(2))
    white = white_balance(numerator, denominator, info, clipped, layout.share, spread)
    values, own = np.empty((3, hc, wc), f32), np.empty((3, hc, wc), f32)
    scratch = np.empty(wc, f32)
    for i in range(hc):
        _cell_values_row(numerator, denominator, mean, info, bound, white, values, i, i)
        _cell_values_row(weighted, kept, mean, info, bound, white, own, i, i)

    def centred(planes: np.ndarray) -> np.ndarray:
        out = np.empty_like(planes)
        for c, (ky, kx) in enumerate(S._centring_kernels(layout)):
            cv2.sepFilter2D(planes[c], cv2.CV_32F, kx, ky, dst=out[c], borderType=cv2.BORDER_REPLICATE)
        return out

    shares, own_shares = centred(values), centred(own)
    neutral = (white / f32(layout.share @ white)).astype(f32)
    coarse = np.empty((2, hc, wc), f32)
    noise, own_noise, deviation, residual = (np.empty((3, hc, wc), f32) for _ in range(4))
    for i in range(hc):
        S._shares_row(shares, info, bound, censored, layout.share, neutral, f32(S.SHARE_FLOOR), spread, coarse,
                      noise, i, i, i)
        S._own_shares_row(own_shares, info, layout.share, neutral, f32(S.SHARE_FLOOR), shares, own_noise, residual,
                          scratch, i, i)
    for c in range(3):
        cv2.sepFilter2D(residual[c], cv2.CV_32F, k, k, dst=residual[c], borderType=cv2.BORDER_REFLECT_101)
    for i in range(hc):
        S._blend_row(shares, noise, own_shares, own_noise, residual, neutral, deviation, i)
    for c in range(3):
        cv2.sepFilter2D(deviation[c], cv2.CV_32F, k, k, dst=deviation[c], borderType=cv2.BORDER_REFLECT_101)
    for i in range(hc):
        S._shrink_row(shares, neutral, noise, deviation, i)
    for c in range(3):
        cv2.medianBlur(shares[c], 3, dst=shares[c])
    for i in range(hc):
        S._normalise_row(shares, layout.share, f32(S.SHARE_FLOOR), scratch, i)
    return shares, coarse, white


@pytest.mark.parametrize("layout", list(COLOUR_LAYOUTS))
@pytest.mark.parametrize("stops", [0.0, 5.0])
@pytest.mark.parametrize("shape", [(64, 96), (37, 53), (9, 14), (4, 4), (1, 8), (16, 1)])
def test_one_pass_is_the_whole_plane_chain_bit_for_bit(layout, stops, shape):
    pattern, cfa = COLOUR_LAYOUTS[layout]
    rgb = np.maximum(load_sample_scene("desk", rgb=True), 0)[40:40 + shape[0], 60:60 + shape[1]]
    # 2 stops over the fill at "bright": the long exposures clip, so the censoring rules are exercised
    scale = np.float32(exposure_scale(rgb, Pattern.parse(pattern), SENSOR, stops_below_fill=stops - 2))
    frame = simulate(rgb * scale, pattern, SENSOR, cfa=cfa, seed=11)
    inp = prepare(frame.raw, Camera.build(pattern, cfa, SENSOR))
    got = chroma(inp)
    shares, coarse, white = _whole_planes(inp)
    np.testing.assert_array_equal(got.white, white)
    np.testing.assert_array_equal(got.coarse, coarse)
    np.testing.assert_array_equal(got.shares, shares)
    # with the white balance given (a stream's partial chroma): the statistics, the smoothing and the censoring in
    # the share pass's own rings of cell rows (_chroma_pass)
    given = chroma(inp, white)
    np.testing.assert_array_equal(given.coarse, coarse)
    np.testing.assert_array_equal(given.shares, shares)
    if stops == 0.0 and min(shape) > 8:
        assert np.count_nonzero(inp.censored) > 0  # the clipped case is the one tested


@pytest.mark.parametrize("layout", list(COLOUR_LAYOUTS))
@pytest.mark.parametrize("stops", [0.0, 5.0])
def test_partial_chroma_is_the_whole_frames_on_its_cell_rows_and_the_history_elsewhere(layout, stops):
    """colour.partial_chroma (a still colour stream's band refresh): on the cell rows it makes, the whole frame's
    chroma with the same white balance, bit for bit (its crops' CHROMA_HALO cell rows are what the passes read:
    one fewer differs on a bright frame); elsewhere the history's planes, exactly; runs at the frame's edges, apart
    and of one row."""
    pattern, cfa = COLOUR_LAYOUTS[layout]
    rgb = np.maximum(load_sample_scene("desk", rgb=True), 0)[:150, :120]
    scale = np.float32(exposure_scale(rgb, Pattern.parse(pattern), SENSOR, stops_below_fill=stops - 2))
    inp = prepare(simulate(rgb * scale, pattern, SENSOR, cfa=cfa, seed=11).raw, Camera.build(pattern, cfa, SENSOR))
    whole = chroma(inp, np.array([0.9, 1.0, 1.2], np.float32))
    assert not np.array_equal(whole.shares, chroma(inp).shares)  # (the white given is taken)
    hc = whole.shares.shape[1]
    history = np.random.default_rng(3).random((5, *whole.shares.shape[1:]), dtype=np.float32)
    for runs in ([(0, 3)], [(2, 9), (hc - 12, hc - 5)], [(hc - 4, hc)], [(hc // 2, hc // 2 + 1)], [(0, hc)]):
        got = S.partial_chroma(inp, runs, history, whole.white)
        made = np.zeros(hc, bool)
        for a, b in runs:
            made[a:b] = True
        np.testing.assert_array_equal(got.shares[:, made], whole.shares[:, made])
        np.testing.assert_array_equal(got.coarse[:, made], whole.coarse[:, made])
        np.testing.assert_array_equal(got.shares[:, ~made], history[:3, ~made])
        np.testing.assert_array_equal(got.coarse[:, ~made], history[3:, ~made])
        np.testing.assert_array_equal(got.white, whole.white)
        assert got.planes is not None  # (one array of both: the stream's fusion takes it in place)
        assert np.shares_memory(got.planes, got.shares) and np.shares_memory(got.planes, got.coarse)
    assert whole.planes is not None  # (a whole frame's too)
    assert S.Chroma(whole.shares.copy(), whole.coarse.copy(), whole.layout, whole.white, whole.shape).planes is None
    if stops == 0.0:  # (the dim frame's shares are flat enough that a shorter reach may still agree)
        halo, S.CHROMA_HALO = S.CHROMA_HALO, S.CHROMA_HALO - 1
        try:
            short = S.partial_chroma(inp, [(hc // 2, hc // 2 + 1)], history, whole.white)
        finally:
            S.CHROMA_HALO = halo
        assert not np.array_equal(short.shares[:, hc // 2], whole.shares[:, hc // 2])


def test_the_pass_filters_match_opencv_on_random_planes():
    """The pass's filters alone, on planes with every kind of value (their own drivers: rows of a plane)."""
    rng = np.random.default_rng(5)
    k = binomial_kernel(3)
    taps = np.array([[0.31944445, 0.6805556, 0.0], [0.25, 0.75, 0.0]], np.float32)
    for h, w in ((300, 96), (7, 13), (2, 3), (1, 1), (1, 5), (5, 1)):
        plane = (rng.standard_normal((h, w)) * 1e3).astype(np.float32)
        along = np.empty_like(plane)
        out = np.empty_like(plane)
        for i in range(h):
            S._binomial_along(plane[i], k, along[i])
        for i in range(h):
            S._binomial_across(along[S._mirrored(i - 1, h)], along[i], along[S._mirrored(i + 1, h)], k, out[i])
        np.testing.assert_array_equal(out, cv2.sepFilter2D(plane, cv2.CV_32F, k, k,
                                                           borderType=cv2.BORDER_REFLECT_101))
        for i in range(h):
            S._taps_along(plane[i], taps[1], along[i])
        for i in range(h):
            S._taps_across(along[max(i - 1, 0)], along[i], along[min(i + 1, h - 1)], taps[0], out[i])
        np.testing.assert_array_equal(out, cv2.sepFilter2D(plane, cv2.CV_32F, taps[1], taps[0],
                                                           borderType=cv2.BORDER_REPLICATE))
        columns = np.empty((3, w), np.float32)
        for i in range(h):
            S._median_row(plane[max(i - 1, 0)], plane[i], plane[min(i + 1, h - 1)], out[i], columns)
        np.testing.assert_array_equal(out, cv2.medianBlur(plane, 3))


def test_the_cells_values_follow_the_highlight_rules_on_random_planes():
    """highlights._cell_values_row against the rules as whole-plane numpy (the pass's reference above calls it):
    cells with censored readings, clipped channels raised to the measured ones' white level, cells whose every
    channel is only a bound, edge cells without a channel's pixels."""
    rng = np.random.default_rng(8)
    f32 = np.float32
    for wc in (1, 7, 64):
        numerator, denominator, mean, info, bound = (rng.uniform(-1, 5, (3, 4, wc)).astype(f32) for _ in range(5))
        for plane in (denominator, info, bound):
            plane[rng.random(plane.shape) < 0.4] = 0
        numerator[:, 0, 0] = np.inf
        info[:, 1, -1], bound[:, 1, -1] = 0, 2  # every channel only a bound: neutral white
        info[:, 2, 0], bound[:, 2, 0] = 1, 0  # every channel measured ...
        info[1, 2, 0], bound[1, 2, 0] = 0, 3  # ... but green, clipped: raised to the others' white level
        white = np.array([1.7, 1.0, 0.6], f32)
        out = np.empty((3, 2, wc), f32)
        smoothed = np.where(denominator > 0, numerator / np.where(denominator > 0, denominator, 1), f32(0))
        value = np.maximum(np.where(bound > 0, np.maximum(mean, bound), smoothed), f32(0))
        measured = (info > 0) | ((bound <= 0) & (denominator > 0))
        inverse = (f32(1) / white)[:, None, None]
        top = np.max(np.where(measured, value * inverse, f32(-1)), axis=0)
        expected = np.where(measured, value, np.maximum(value, white[:, None, None] * top))
        neutral = white[:, None, None] * np.max(expected / white[:, None, None], axis=0)
        expected = np.where(top < 0, neutral, expected)
        assert top[1, -1] < 0 and not measured[1, 2, 0] and measured[[0, 2], 2, 0].all()
        for i in range(4):
            _cell_values_row(numerator, denominator, mean, info, bound, white, out, i, i % 2)
            np.testing.assert_array_equal(out[:, i % 2], expected[:, i])


@pytest.mark.parametrize("layout", ["dual-iso", "quad-bayer"])
def test_refine_colours_its_result_as_colourise_does(layout):
    """``refine(..., rgb=)`` (a stream's fused luminance coloured in the refinement's pass) is bit for bit
    ``colourise`` of the refined luminance, with and without a history weight and over threads."""
    from concurrent.futures import ThreadPoolExecutor

    from svelive.reconstruction.colour import colourise, interpolation, refine
    pattern, cfa = COLOUR_LAYOUTS[layout]
    rgb = np.maximum(load_sample_scene("desk", rgb=True), 0)[:150, :200]
    scale = np.float32(exposure_scale(rgb, Pattern.parse(pattern), SENSOR, stops_below_fill=3))
    inp = prepare(simulate(rgb * scale, pattern, SENSOR, cfa=cfa, seed=2).raw, Camera.build(pattern, cfa, SENSOR))
    ch = chroma(inp)
    inter = interpolation(ch, coarse=True)
    rng = np.random.default_rng(0)
    luminance = (rgb @ np.array([0.25, 0.5, 0.25], np.float32) * scale).astype(np.float32)
    variance = (luminance / 10 + 4 + rng.random(luminance.shape, np.float32)).astype(np.float32)
    weight = rng.random(luminance.shape, np.float32)
    with ThreadPoolExecutor(2) as pool:
        for w in (None, weight):
            for workers in (1, pool):
                out = np.empty((*luminance.shape, 3), np.float32)
                refined = refine(luminance, variance, inter, ch.layout.cell, weight=w, rgb=out, workers=workers)
                np.testing.assert_array_equal(refined, refine(luminance, variance, inter, ch.layout.cell, weight=w))
                np.testing.assert_array_equal(out, colourise(refined, inter))
    with pytest.raises(ValueError):
        refine(luminance, variance, inter, ch.layout.cell, out=np.empty_like(luminance), rgb=out)


def test_refine_takes_a_floor_under_the_variance_where_the_weight_is_below_one():
    """``refine(..., floor=)`` (a stream's measured noise per cell row and column) is bit for bit ``refine`` of the
    variance raised to the floor where the weight is below 1, over threads."""
    from concurrent.futures import ThreadPoolExecutor

    from svelive.reconstruction.colour import interpolation, refine
    pattern, cfa = COLOUR_LAYOUTS["dual-iso"]
    rgb = np.maximum(load_sample_scene("desk", rgb=True), 0)[:150, :200]
    scale = np.float32(exposure_scale(rgb, Pattern.parse(pattern), SENSOR, stops_below_fill=3))
    inp = prepare(simulate(rgb * scale, pattern, SENSOR, cfa=cfa, seed=2).raw, Camera.build(pattern, cfa, SENSOR))
    ch = chroma(inp)
    inter, (cy, _) = interpolation(ch, coarse=True), ch.layout.cell
    rng = np.random.default_rng(1)
    luminance = (rgb @ np.array([0.25, 0.5, 0.25], np.float32) * scale).astype(np.float32)
    variance = (luminance / 10 + 4 + rng.random(luminance.shape, np.float32)).astype(np.float32)
    weight = rng.random(luminance.shape, np.float32)
    weight[:, ::5] = 1
    floor = (4 + 8 * rng.random((-(-luminance.shape[0] // cy), luminance.shape[1]), np.float32)).astype(np.float32)
    raised = np.where(weight < 1, np.maximum(variance, np.repeat(floor, cy, axis=0)[:luminance.shape[0]]), variance)
    assert np.any(raised != variance) and np.any((raised == variance) & (weight < 1))
    expected = refine(luminance, raised, inter, ch.layout.cell, weight=weight)
    with ThreadPoolExecutor(2) as pool:
        for workers in (1, pool):
            out = np.empty((*luminance.shape, 3), np.float32)
            got = refine(luminance, variance, inter, ch.layout.cell, weight=weight, floor=floor, rgb=out,
                         workers=workers)
            np.testing.assert_array_equal(got, expected)
    with pytest.raises(ValueError):
        refine(luminance, variance, inter, ch.layout.cell, floor=floor)


def test_colourise_copies_the_luminance_in_its_pass():
    from svelive.reconstruction.colour import colourise, interpolation
    pattern, cfa = COLOUR_LAYOUTS["dual-iso"]
    rgb = np.maximum(load_sample_scene("desk", rgb=True), 0)[:64, :96]
    scale = np.float32(exposure_scale(rgb, Pattern.parse(pattern), SENSOR))
    inp = prepare(simulate(rgb * scale, pattern, SENSOR, cfa=cfa, seed=2).raw, Camera.build(pattern, cfa, SENSOR))
    inter = interpolation(chroma(inp))
    luminance = np.random.default_rng(1).random((64, 96), np.float32)
    copy = np.full_like(luminance, np.nan)
    np.testing.assert_array_equal(colourise(luminance, inter, copy=copy), colourise(luminance, inter))
    np.testing.assert_array_equal(copy, luminance)
