"""Colour SVE: simulation through a colour filter, joint and split reconstruction (issue 11, section 3).

Scenes are the shipped 256x256 RGB crops (cropped further for speed) or synthetic.
"""

from __future__ import annotations

import numpy as np
import pytest

import svelive
from svelive import Camera, Pattern, Sensor, SveliveError, simulate
from svelive.core.camera import COLOUR_LAYOUTS
from svelive.core.cfa import PRESETS, ColourFilter
from svelive.metrics import pu21_psnr_colour
from svelive.reconstruction import colour
from svelive.reconstruction.colour import run_colour
from svelive.reconstruction.input import prepare
from svelive.reconstruction.methods import METHODS
from svelive.simulation import SAMPLE_SCENES, exposure_scale, load_sample_scene

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


# ----- reconstruction -------------------------------------------------------------------

KW = dict(white_level=SENSOR.white_level, gain=SENSOR.gain, read_noise=SENSOR.read_noise)
BRIGHTNESS = {"bright": 0.0, "dim": 5.0}


def crop_frame(name: str, layout: str, stops: float, seed: int = 3):
    """A shipped crop (RGB) simulated through a colour layout; (pattern, cfa, frame)."""
    pattern, cfa = COLOUR_LAYOUTS[layout]
    rgb = np.maximum(load_sample_scene(name, rgb=True), 0)
    radiance = rgb * np.float32(exposure_scale(rgb, Pattern.parse(pattern), SENSOR, stops_below_fill=stops))
    return pattern, cfa, simulate(radiance, pattern, SENSOR, cfa=cfa, seed=seed)


def block_means(image: np.ndarray, n: int = 8) -> np.ndarray:
    h, w = image.shape[:2]
    return image[:h // n * n, :w // n * n].reshape(h // n, n, w // n, n, *image.shape[2:]).mean(axis=(1, 3))


def chromaticity(rgb: np.ndarray) -> np.ndarray:
    return rgb / np.maximum(rgb.sum(axis=-1, keepdims=True), 1e-12)


@pytest.mark.parametrize("shape", [(37, 53), (16, 1), (5, 2)])
@pytest.mark.parametrize("layout", list(COLOUR_LAYOUTS))
def test_folded_exposure_is_e_times_its_channels_interpolated_share_bit_for_bit(layout, shape):
    """The fold's kernel (a CFA of two columns: both channels of a row interpolated, chosen by parity; else
    the pixel's channel chosen first) against numpy's float32 arithmetic."""
    pattern, cfa, frame = crop_frame("desk", layout, 0.0)
    inp = prepare(frame.raw[:shape[0], :shape[1]], Camera.build(pattern, cfa, SENSOR))
    inter = colour.interpolation(colour.chroma(inp))
    rows = np.arange(inp.shape[0])[:, None]
    channel = inp.cfa.channel_map(inp.shape)
    a = inter.rows[channel, inter.top[rows], np.arange(inp.shape[1])]
    b = inter.rows[channel, np.minimum(inter.top + 1, inter.rows.shape[1] - 1)[rows], np.arange(inp.shape[1])]
    expected = inp.exposure * (a + (b - a) * inter.frac[rows])
    np.testing.assert_array_equal(colour.folded_exposure(inp, inter), expected)


@pytest.mark.parametrize("shape", [(150, 200), (131, 197), (9, 7)])
@pytest.mark.parametrize("layout", [*COLOUR_LAYOUTS, "1,4,16"])
def test_passes_widen_their_pieces_cell_rows_as_the_whole_interpolation(layout, shape):
    """Interpolation.piece_rows (each piece of a pass widening only the cell rows it lies between) gives the whole
    rows' values, and the fold, the refinement (its residual cells made per piece too) and the colour are bit for bit
    those from whole rows made first (``whole``), over pieces of rows and two threads. "1,4,16" with RGGB: cells of
    6 columns (OpenCV's resize)."""
    from concurrent.futures import ThreadPoolExecutor

    from svelive.reconstruction.colour.interpolate import _pieces
    pattern, cfa = COLOUR_LAYOUTS.get(layout, (layout, "RGGB"))
    rgb = np.maximum(load_sample_scene("desk", rgb=True), 0)[:shape[0], :shape[1]]
    scale = np.float32(exposure_scale(rgb, Pattern.parse(pattern), SENSOR, stops_below_fill=3))
    inp = prepare(simulate(rgb * scale, pattern, SENSOR, cfa=cfa, seed=2).raw, Camera.build(pattern, cfa, SENSOR))
    ch = colour.chroma(inp)
    whole, pieces = colour.interpolation(ch, coarse=True, whole=True), colour.interpolation(ch, coarse=True)
    h = shape[0]
    for rows in [*_pieces(h), slice(0, h), slice(h - 1, h), slice(h // 3, h // 2 + 1)]:
        planes, first = pieces.piece_rows(rows)
        assert first == pieces.top[rows.start] and planes.shape[1] >= 1
        np.testing.assert_array_equal(planes, whole.rows[:, first:first + planes.shape[1]])
        np.testing.assert_array_equal(pieces.top[rows] - first >= 0, True)
        assert np.minimum(pieces.top[rows] + 1, whole.rows.shape[1] - 1).max() < first + planes.shape[1]
    luminance = (rgb @ np.array([0.25, 0.5, 0.25], np.float32) * scale).astype(np.float32)
    variance = (luminance / 10 + 4).astype(np.float32)
    weight = np.random.default_rng(0).random(luminance.shape, np.float32)
    with ThreadPoolExecutor(2) as pool:
        for workers in (1, pool):
            got, expected = (np.empty((*shape, 3), np.float32) for _ in range(2))
            np.testing.assert_array_equal(
                colour.refine(luminance, variance, pieces, ch.layout.cell, weight=weight, rgb=got, workers=workers),
                colour.refine(luminance, variance, whole, ch.layout.cell, weight=weight, rgb=expected, workers=workers))
            np.testing.assert_array_equal(got, expected)
            np.testing.assert_array_equal(colour.folded_exposure(inp, colour.interpolation(ch), workers),
                                          colour.folded_exposure(inp, colour.interpolation(ch, whole=True), workers))
            np.testing.assert_array_equal(colour.colourise(luminance, colour.interpolation(ch), workers),
                                          colour.colourise(luminance, whole, workers))
    assert "rows" not in pieces.__dict__  # (the passes above made their pieces' rows, not the whole ones)


@pytest.mark.parametrize("stops", BRIGHTNESS.values(), ids=BRIGHTNESS.keys())
@pytest.mark.parametrize("layout", list(COLOUR_LAYOUTS))
def test_every_colour_layout_reconstructs_finite_and_to_scale_per_channel(layout, stops):
    """The median over the crops' well-exposed 8x8 blocks (every pixel at SNR >= 10 in the longest
    exposure by the noise model, unclipped in the shortest) of the ratio of block means, per channel."""
    ratios = [[], [], []]
    for name in SAMPLE_SCENES:
        pattern, cfa, frame = crop_frame(name, layout, stops)
        image = svelive.reconstruct(frame.raw, pattern, cfa=cfa, **KW)
        assert image.shape == frame.truth.shape and image.dtype == np.float32
        assert np.all(np.isfinite(image)) and image.min() >= 0
        tile = Pattern.parse(pattern).tile
        signal = frame.truth * tile.max()
        snr = signal / np.sqrt(signal / SENSOR.gain + SENSOR.floor_variance)
        well = np.all((snr >= 10) & (frame.truth * tile.min() < SENSOR.censor_level), axis=2)
        blocks = block_means(well.astype(np.float32)) == 1
        truth, estimate = block_means(frame.truth), block_means(image)
        for c in range(3):
            ratios[c].extend(estimate[..., c][blocks] / truth[..., c][blocks])
    assert len(ratios[0]) >= 20
    for c in range(3):
        assert np.median(ratios[c]) == pytest.approx(1.0, abs=0.02), "RGB"[c]


@pytest.mark.parametrize("cfa", [*PRESETS, "R,G,B/G,B,R"])
@pytest.mark.parametrize("mode", ["joint", "split"])
def test_every_colour_filter_puts_each_channel_where_it_belongs(cfa, mode):
    # a saturated colour in each channel in turn: a wrong phase would mix them up
    for c in range(3):
        rgb = np.full((50, 38, 3), 30.0, np.float32)
        rgb[..., c] = 300.0
        frame = simulate(rgb, "1/1/8/8", SENSOR, cfa=cfa, seed=c)
        image = svelive.reconstruct(frame.raw, "1/1/8/8", cfa=cfa, colour=mode, **KW)
        assert image.shape == (50, 38, 3) and np.all(np.isfinite(image)) and image.min() >= 0
        inner = image[8:-8, 8:-8].reshape(-1, 3).mean(axis=0)
        np.testing.assert_allclose(inner, rgb[0, 0], rtol=0.03)


@pytest.mark.parametrize("method", ["adaptive", "weighted", "aggregate", "cubic"])
@pytest.mark.parametrize("mode", ["joint", "split"])
def test_every_method_runs_on_colour_frames_with_confidence(method, mode):
    pattern, cfa, frame = crop_frame("cannon", "dual-iso", 0.0)
    raw, truth = frame.raw[:48, :40], frame.truth[:48, :40]
    image, confidence = svelive.reconstruct(raw, pattern, cfa=cfa, method=method, colour=mode,
                                            return_confidence=True, **KW)
    assert image.shape == (48, 40, 3) and confidence.shape == (48, 40)
    assert np.all(np.isfinite(image)) and image.min() >= 0
    assert 0 <= confidence.min() and confidence.max() <= 1
    assert np.median(image / np.maximum(truth, 1e-6)) == pytest.approx(1.0, abs=0.1)


@pytest.mark.parametrize("mode", ["joint", "split"])
def test_per_pixel_exposure_maps_work_with_a_colour_filter(mode):
    nominal = Pattern.parse("1/1/8/8")
    rng = np.random.default_rng(4)
    pixel_map = nominal.exposure_map((64, 48)) * rng.uniform(1.05, 1.25, (64, 48)).astype(np.float32)
    calibrated = nominal.with_pixel_map(pixel_map)
    rgb = np.empty((64, 48, 3), np.float32)
    rgb[...] = (120.0, 200.0, 90.0)
    frame = simulate(rgb, calibrated, SENSOR, cfa="RGGB", seed=2)  # the sensor's true exposures
    with_map = svelive.reconstruct(frame.raw, calibrated, cfa="RGGB", colour=mode, **KW)
    without = svelive.reconstruct(frame.raw, nominal, cfa="RGGB", colour=mode, **KW)
    for c in range(3):
        assert np.median(with_map[8:-8, 8:-8, c]) == pytest.approx(rgb[0, 0, c], rel=0.02)
    assert np.median(without[8:-8, 8:-8] / with_map[8:-8, 8:-8]) > 1.1  # the map matters


def test_grey_scene_shows_no_false_colour_beyond_the_chroma_noise():
    """Flat grey at levels where no reading comes near the censor level: the spread of log(R/G) and
    log(B/G) is at most what the noise model predicts for one cell's chroma (the inverse-variance
    mean of each channel's readings in a cell, smoothed over 3x3 cells with [1, 2, 1] / 4 weights,
    whose squared weights sum to (6/16)^2; interpolating between cells only lowers it), and their
    mean is within 4 standard errors of 0 (one cell in 3x3 counted as independent)."""
    for layout, (pattern, cfa) in COLOUR_LAYOUTS.items():
        p, f = Pattern.parse(pattern), ColourFilter.parse(cfa)
        cell = (np.lcm(p.shape[0], f.shape[0]), np.lcm(p.shape[1], f.shape[1]))
        exposure = p.exposure_map(cell).astype(np.float64)
        channels = f.channel_map(cell)
        for level in (5.0, 50.0):
            assert level * p.tile.max() + 4 * np.sqrt(SENSOR.signal_variance(level * p.tile.max())) < SENSOR.censor_level
            variance = (exposure * level / SENSOR.gain + SENSOR.floor_variance) / exposure ** 2
            cell_variance = [1 / np.sum(1 / variance[channels == c]) * (6 / 16) ** 2 for c in range(3)]
            frame = simulate(np.full((128, 128, 3), level, np.float32), pattern, SENSOR, cfa=cfa, seed=7)
            image = svelive.reconstruct(frame.raw, pattern, cfa=cfa, **KW)[8:-8, 8:-8]
            cells = image.shape[0] * image.shape[1] / (cell[0] * cell[1] * 9)
            for c in (0, 2):
                log_ratio = np.log(image[..., c] / image[..., 1])
                predicted = np.sqrt(cell_variance[c] + cell_variance[1]) / level
                assert log_ratio.std() <= predicted, (layout, level, "RGB"[c])
                assert abs(log_ratio.mean()) <= 4 * predicted / np.sqrt(cells), (layout, level, "RGB"[c])


@pytest.mark.parametrize("layout", list(COLOUR_LAYOUTS))
def test_clipped_white_highlight_where_only_green_clips_stays_white_not_magenta(layout):
    """A white object whose green clips in every exposure while red and blue are measured (camera
    white 0.55 : 1 : 0.7, green the most sensitive) keeps the hue of white."""
    pattern, cfa = COLOUR_LAYOUTS[layout]
    p = Pattern.parse(pattern)
    white = np.array([0.55, 1.0, 0.7], np.float32)
    n = 96
    yy, xx = np.mgrid[:n, :n]
    radius2 = (yy - n / 2) ** 2 + (xx - n / 2) ** 2
    level = np.where(radius2 <= 20 ** 2, 1.25 * SENSOR.white_level / p.tile.min(), 0.3 * SENSOR.range_dn / p.tile.max())
    frame = simulate((level[..., None] * white).astype(np.float32), pattern, SENSOR, cfa=cfa, seed=6)
    inner = radius2 <= 14 ** 2
    channels = ColourFilter.parse(cfa).channel_map((n, n))
    assert np.all(frame.raw[inner & (channels == 1)] >= SENSOR.censor_level)  # green clipped everywhere
    assert np.all(frame.raw[inner & (channels != 1) & (p.exposure_map((n, n)) == p.tile.min())] < SENSOR.censor_level)
    image = svelive.reconstruct(frame.raw, pattern, cfa=cfa, **KW)
    hue = chromaticity(image[inner]).mean(axis=0)
    np.testing.assert_allclose(hue, chromaticity(white), atol=0.01)


def slanted_edge(layout: str, n: int = 96):
    """A neutral black-to-white edge 5 degrees off vertical (white at 60 % of the shortest
    exposure's range, black 30 times darker), its signed distance (px), and the frame."""
    pattern, cfa = COLOUR_LAYOUTS[layout]
    yy, xx = np.mgrid[:n, :n].astype(np.float32)
    distance = (xx - n / 2) * np.cos(np.deg2rad(5)) - (yy - n / 2) * np.sin(np.deg2rad(5))
    fill = SENSOR.range_dn / Pattern.parse(pattern).tile.min()
    luminance = (0.02 + 0.58 * np.clip(distance + 0.5, 0, 1)) * fill
    frame = simulate(np.repeat(luminance[..., None], 3, axis=2), pattern, SENSOR, cfa=cfa, seed=5)
    return pattern, cfa, distance, frame


@pytest.mark.parametrize("layout", list(COLOUR_LAYOUTS))
def test_slanted_edge_shows_less_false_colour_than_the_split_baseline(layout):
    pattern, cfa, distance, frame = slanted_edge(layout)
    n = distance.shape[0]
    band = np.abs(distance) <= 4
    band[:8], band[n - 8:] = False, False
    false_colour = {}
    for mode in ("joint", "split"):
        image = svelive.reconstruct(frame.raw, pattern, cfa=cfa, colour=mode, **KW)
        false_colour[mode] = np.abs(chromaticity(image[band]) - 1 / 3).sum(axis=-1).mean()
    assert false_colour["joint"] < false_colour["split"]


@pytest.mark.parametrize("stops", [2, 3, 4])
@pytest.mark.parametrize("layout", list(COLOUR_LAYOUTS))
def test_cells_beside_a_neutral_edge_keep_a_neutral_surfaces_shares(layout, stops):
    """A neutral edge (camera white 0.5 : 1 : 0.7, the dark side at a quarter of the longest
    exposure's range) has the same shares k_c on both sides; a cell whose channels read
    different sides of it (its samples, smoothed and centred, straddle the edge) gets wrong
    ones, and the luminance folded with them zips along the edge. At 99 % of the cells the
    shares stay within 20 % of the neutral's (before the cells' median: 22-55 % at 2-4 stops)."""
    pattern, cfa = COLOUR_LAYOUTS[layout]
    white = np.array([0.5, 1.0, 0.7], np.float32)
    n = 96
    yy, xx = np.mgrid[:n, :n].astype(np.float32)
    distance = (xx - n / 2) * np.cos(np.deg2rad(5)) - (yy - n / 2) * np.sin(np.deg2rad(5))
    dark = 0.25 * SENSOR.range_dn / Pattern.parse(pattern).tile.max()
    level = np.where(distance > 0, dark * 2.0 ** stops, dark)
    frame = simulate((level[..., None] * white).astype(np.float32), pattern, SENSOR, cfa=cfa, seed=5)
    ch = colour.chroma(prepare(frame.raw, Camera.build(layout, sensor=SENSOR)))
    neutral = white / (ch.layout.share @ white)
    deviation = np.abs(np.log(ch.shares / neutral[:, None, None]))
    assert np.percentile(deviation, 99) <= np.log(1.2), np.percentile(deviation, 99)


@pytest.mark.parametrize("layout", list(COLOUR_LAYOUTS))
def test_bright_colour_stripes_three_cells_wide_keep_their_shares(layout):
    """Vertical stripes of two colours (1 : 0.5 : 0.3 and 0.3 : 0.5 : 1), three cells wide, bright
    and unclipped: the 3x3 cells' smoothing mixes the stripes in every cell beside a border, and
    each cell's own readings show the difference far beyond their noise, so the shares follow
    them. Mean |log| error of the shares at the cells' centres (frame border left out) at most
    0.15 (0.18-0.20 with the smoothed shares alone, 0.22-0.24 after the median of the cells)."""
    pattern, cfa = COLOUR_LAYOUTS[layout]
    camera = Camera.build(layout, sensor=SENSOR)
    cx = colour.cell_layout(camera.require_pattern(), camera.cfa).cell[1]
    n = 96
    stripe = (np.arange(n) // (3 * cx)) % 2
    a, b = np.array([1.0, 0.5, 0.3], np.float32), np.array([0.3, 0.5, 1.0], np.float32)
    rgb = np.where(stripe[None, :, None] == 0, a, b) * np.ones((n, 1, 1), np.float32)
    level = 0.5 * SENSOR.range_dn / Pattern.parse(pattern).tile.max()
    frame = simulate((rgb * level).astype(np.float32), pattern, SENSOR, cfa=cfa, seed=7)
    ch = colour.chroma(prepare(frame.raw, camera))
    ka, kb = a / (ch.layout.share @ a), b / (ch.layout.share @ b)
    centres = (np.arange(ch.shares.shape[2]) * cx + (cx - 1) / 2).astype(int)
    truth = np.where(stripe[centres] == 0, ka[:, None], kb[:, None])[:, None, :]
    error = np.abs(np.log(ch.shares / truth))[:, 2:-2, 2:-2]
    assert error.mean() <= 0.15, error.mean()


@pytest.mark.parametrize("stops", BRIGHTNESS.values(), ids=BRIGHTNESS.keys())
@pytest.mark.parametrize("layout", list(COLOUR_LAYOUTS))
def test_joint_beats_split_in_pu21_on_luminance_over_the_crops(layout, stops):
    scores = {"joint": [], "split": []}
    for name in SAMPLE_SCENES:
        pattern, cfa, frame = crop_frame(name, layout, stops)
        for mode in scores:
            image = svelive.reconstruct(frame.raw, pattern, cfa=cfa, colour=mode, **KW)
            scores[mode].append(pu21_psnr_colour(image, frame.truth)["Y"])
    assert np.mean(scores["joint"]) > np.mean(scores["split"])


def test_colour_arguments_are_checked_in_one_line():
    frame = simulate(np.full((16, 16, 3), 50.0, np.float32), "1/1/8/8", SENSOR, cfa="RGGB")
    for call, word in ((lambda: svelive.reconstruct(frame.raw, "1/1/8/8", cfa="RGGB", colour="both"), "colour"),
                       (lambda: svelive.reconstruct(frame.raw, "1/1/8/8", cfa="RGGX"), "RGGX")):
        with pytest.raises(SveliveError) as error:
            call()
        assert word in str(error.value) and "\n" not in str(error.value)
    mono = prepare(frame.raw, Camera.build("1/1/8/8"))
    with pytest.raises(SveliveError, match="colour filter"):
        run_colour(mono, METHODS["adaptive"], "joint")


def test_a_colour_camera_stands_for_pattern_and_filter():
    camera = Camera.build("dual-iso", sensor=SENSOR)
    frame = simulate(np.full((32, 32, 3), 80.0, np.float32), camera.pattern, SENSOR, cfa=camera.cfa, seed=1)
    np.testing.assert_array_equal(svelive.reconstruct(frame.raw, camera),
                                  svelive.reconstruct(frame.raw, "1/1/8/8", cfa="RGGB", **KW))


def test_a_channel_at_zero_over_a_bright_area_stays_finite():
    """A synthetic frame (a test camera's) may hold green and blue at 0 where red is bright: the
    white balance must not divide by them."""
    rgb = np.zeros((64, 64, 3), np.float32)
    rgb[:, :32, 0] = 400.0
    rgb[:, 32:] = 60.0
    frame = simulate(rgb, "1/1/8/8", Sensor(12, gain=1e6, read_noise=0.0), cfa="RGGB", seed=1)
    for mode in ("joint", "split"):
        image = svelive.reconstruct(frame.raw, "1/1/8/8", cfa="RGGB", colour=mode, **KW)
        assert np.all(np.isfinite(image)) and image.min() >= 0
    stream = svelive.Reconstructor("1/1/8/8", cfa="RGGB", **KW)
    for _ in range(2):
        result = stream.process(frame.raw)
    assert np.all(np.isfinite(result.image)) and np.all(np.isfinite(result.variance))
    assert result.image[8:-8, 8:24, 0].mean() == pytest.approx(400.0, rel=0.05)


@pytest.mark.parametrize("peak", [0.5, 0.75, 1.5])
@pytest.mark.parametrize("layout", list(COLOUR_LAYOUTS))
def test_gaussian_highlight_on_a_dim_ground_stays_white(layout, peak):
    """A white Gaussian highlight (camera white 0.5 : 1 : 0.7) rising above the shortest exposure's
    range on a dim grey ground, in a small frame (few cells for the white balance; on assorted-4x4
    the 64x exposure clips over the whole ground): green may not fall behind red or blue by more
    than 0.1 stop inside it, where green clips in every exposure."""
    pattern, cfa = COLOUR_LAYOUTS[layout]
    white = np.array([0.5, 1.0, 0.7], np.float32)
    y, x = np.mgrid[0:96, 0:96].astype(np.float32) - 47.5
    profile = np.exp(-(x * x + y * y) / (2 * 14.0 ** 2))
    full = SENSOR.censor_level / float(Pattern.parse(pattern).levels[0])
    truth = ((full * 2.0 ** peak * profile + 0.02 * full)[..., None] * white).astype(np.float32)
    frame = simulate(truth, pattern, SENSOR, cfa=cfa, seed=17)
    image = svelive.reconstruct(frame.raw, pattern, cfa=cfa, **KW)
    core = profile >= 0.25
    error = np.log2(np.maximum(image[core], 1e-6) / truth[core]).mean(axis=0)  # stops per channel
    assert max(error[0], error[2]) - error[1] <= 0.1


def test_the_joint_colour_checks_the_values_it_writes_and_a_bad_one_is_still_repaired(monkeypatch):
    """single.run_method's guard (finite, >= 0 out) on the joint colour: the refinement's colour pass and the
    lattice flag each row they write a value that is not finite into (instead of a sum over the RGB after them);
    a NaN or inf from the method comes out of run_method repaired, as from any path."""
    from dataclasses import replace

    from svelive.reconstruction.single import run_method
    pattern, cfa = COLOUR_LAYOUTS["dual-iso"]
    rgb = np.maximum(load_sample_scene("desk", rgb=True), 0)[:48, :40]
    scale = np.float32(exposure_scale(rgb, Pattern.parse(pattern), SENSOR, stops_below_fill=3))
    inp = prepare(simulate(rgb * scale, pattern, SENSOR, cfa=cfa, seed=4).raw, Camera.build(pattern, cfa, SENSOR))
    spec = METHODS["adaptive"]
    assert colour.joint(inp, spec).finite
    # the refinement's flags, row by row
    ch = colour.chroma(inp)
    inter = colour.interpolation(ch, coarse=True)
    luminance = (rgb @ np.array([0.25, 0.5, 0.25], np.float32) * scale).astype(np.float32)
    variance = (luminance / 10 + 4).astype(np.float32)
    luminance[3, 5], luminance[17, 0], variance[30, 9] = np.nan, np.inf, np.nan
    image, finite = np.empty((*luminance.shape, 3), np.float32), np.zeros(luminance.shape[0], bool)
    colour.refine(luminance, variance, inter, ch.layout.cell, rgb=image, finite=finite)
    np.testing.assert_array_equal(finite, np.isfinite(image).all(axis=(1, 2)))
    assert not finite[[3, 17, 30]].any() and finite.any()  # (a NaN spreads over its cells' residual)

    def spoilt(inp, **options):
        est = spec.run(inp, **options)
        est.image[5, 7], est.image[20, 3] = np.nan, np.inf
        return est

    monkeypatch.setitem(METHODS, "adaptive", replace(spec, run=spoilt))
    bad = colour.joint(inp, METHODS["adaptive"])
    assert not bad.finite and not np.isfinite(bad.estimate.image).all()
    repaired = np.maximum(np.nan_to_num(bad.estimate.image, nan=0.0, posinf=np.finfo(np.float32).max, neginf=0.0), 0)
    np.testing.assert_array_equal(run_method(inp, "adaptive").image, repaired)


def test_the_lattice_flags_the_rows_it_writes_a_value_that_is_not_finite_into():
    """A red surface: the green and blue pixels' other channels come from their lattices; an infinite red reading
    spreads into the blue pixels at its corners and the green ones above and below it, on the rows around it,
    which the lattice's flags mark (refine's flags, kept valid)."""
    pattern, cfa = COLOUR_LAYOUTS["dual-iso"]
    rgb = np.empty((32, 32, 3), np.float32)
    rgb[:] = (300.0, 2.0, 2.0)
    inp = prepare(simulate(rgb, pattern, SENSOR, cfa=cfa, seed=1).raw, Camera.build(pattern, cfa, SENSOR))
    parts = colour.joint(inp, METHODS["adaptive"], lattice=False)
    image, luminance = parts.estimate.image, parts.estimate.luminance
    r, x = 10, next(x for x in range(8, 16) if inp.channels[10, x] == 0)  # a red pixel
    image[r, x, 0] = np.inf
    finite = np.isfinite(image).all(axis=(1, 2))
    assert colour.lattice_channels(inp, luminance, image, parts.chroma.shares, parts.chroma.layout, finite=finite)
    np.testing.assert_array_equal(finite, np.isfinite(image).all(axis=(1, 2)))
    assert not finite[[r - 1, r, r + 1]].any() and finite.sum() == image.shape[0] - 3


def test_a_caller_that_reads_only_the_image_gets_it_without_the_refined_variance():
    from svelive.reconstruction.single import run_method
    pattern, cfa = COLOUR_LAYOUTS["dual-iso"]
    rgb = np.maximum(load_sample_scene("desk", rgb=True), 0)[:48, :40]
    scale = np.float32(exposure_scale(rgb, Pattern.parse(pattern), SENSOR, stops_below_fill=3))
    inp = prepare(simulate(rgb * scale, pattern, SENSOR, cfa=cfa, seed=4).raw, Camera.build(pattern, cfa, SENSOR))
    full, image_only = run_method(inp), run_method(inp, variance=False)
    assert full.variance is not None and full.variance.shape == inp.shape and image_only.variance is None
    np.testing.assert_array_equal(image_only.image, full.image)
    np.testing.assert_array_equal(image_only.luminance, full.luminance)
