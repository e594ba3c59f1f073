"""Preview tone mapping: curve correctness, no flicker on a static noisy scene, settling after a step."""

from __future__ import annotations

import numpy as np
import pytest

from svelive import Sensor
from svelive.core.errors import SveliveError
from svelive.core.pattern import Pattern
from svelive.reconstruction.single import reconstruct
from svelive.simulation import exposure_scale, load_sample_scene, simulate
from svelive.tonemap import ToneMapper, ToneSettings, ToneStats, srgb_encode

FRAME_NS = 33_333_333  # 30 fps


def noisy_hdr_frames(n: int, seed: int = 0) -> list[np.ndarray]:
    """n reconstructions of one static scene, each from a raw frame with fresh sensor noise."""
    pattern = Pattern.parse("1,4/16,64")
    sensor = Sensor.from_full_well(12, 10_000, 3)
    scene = load_sample_scene("desk")
    radiance = scene * exposure_scale(scene, pattern, sensor, stops_below_fill=1)
    rng = np.random.default_rng(seed)
    return [reconstruct(simulate(radiance, pattern, sensor, seed=rng).raw, pattern, white_level=sensor.white_level,
                        gain=sensor.gain, read_noise=sensor.read_noise) for _ in range(n)]


def reinhard_reference(image: np.ndarray, stats: ToneStats, settings: ToneSettings) -> np.ndarray:
    """The operator evaluated directly in float64, uint8."""
    y = image.astype(np.float64) * settings.key * 2.0 ** (settings.exposure_ev - stats.log2_average)
    y_white = settings.key * 2.0 ** (stats.log2_white - stats.log2_average)
    display = y * (1 + y / y_white**2) / (1 + y)
    return np.rint(srgb_encode(display) * 255).astype(np.uint8)


def test_table_lookup_matches_the_curve_evaluated_directly():
    rng = np.random.default_rng(1)
    image = (2.0 ** rng.uniform(-12, 14, (64, 64))).astype(np.float32)
    image[0, :4] = [0, 1e-30, 3e38, 7.5]
    for settings in (ToneSettings(), ToneSettings(exposure_ev=2.5, key=0.3)):
        mapper = ToneMapper(settings)
        mapper.update(image, 0)
        out = mapper.apply(image)
        ref = reinhard_reference(image, mapper.stats, settings)
        assert out.dtype == np.uint8 and out.shape == image.shape
        # the table quantises radiance in steps of 2**-8 (0.4 %): at most one code value off
        assert np.abs(out.astype(int) - ref).max() <= 1
        assert out[0, 0] == 0 and out[0, 2] == 255


def test_static_noisy_scene_does_not_flicker():
    frames = noisy_hdr_frames(40)
    mapper = ToneMapper(ToneSettings(adapt_s=0.2))
    curve_changes, level_changes = [], []
    previous_lut, previous_mean = None, None
    for i, image in enumerate(frames):
        mapper.update(image, i * FRAME_NS)
        lut = mapper.lut().copy()
        preview = mapper.apply(image)
        if previous_lut is not None:
            index = np.right_shift(image.view(np.uint32), 15)
            # change of the preview caused by the operator alone: same frame, this curve vs the last one
            curve_changes.append(np.abs(lut[index].astype(float) - previous_lut[index]).mean())
            level_changes.append(abs(preview.mean() - previous_mean))
        previous_lut, previous_mean = lut, preview.mean()
    # Bound: half a code value. The display quantises to whole code values, so
    # a mean change below half of one is below what the 8-bit preview can show.
    assert max(curve_changes) < 0.5
    assert max(level_changes) < 0.5


def test_four_stop_step_settles_within_one_second():
    frames = noisy_hdr_frames(8, seed=5)
    mapper = ToneMapper(ToneSettings(adapt_s=0.2))
    step_at, n = 30, 30 + 75
    previews = []
    for i in range(n):
        image = frames[i % len(frames)] * np.float32(16.0 if i >= step_at else 1.0)
        previews.append(mapper(image, i * FRAME_NS).astype(float))
    # the fully adapted preview of the brighter scene: a fresh mapper fed only that scene for 3 s
    settled = ToneMapper(ToneSettings(adapt_s=0.2))
    for i in range(90):
        final = settled(frames[i % len(frames)] * np.float32(16.0), i * FRAME_NS).astype(float)
    errors = [np.abs(previews[i] - final).mean() for i in range(step_at, n)]
    # right after the step the preview is far off: the statistics are smoothed, not taken from one frame ...
    assert errors[0] > 20
    # ... and from 1 s (30 frames) after it on, within 1 % of full scale of the settled preview;
    # fresh noise in every frame alone differs by about a code value, so 2.55 leaves room only for that
    assert max(errors[30:]) < 2.55


def test_gap_restarts_adaptation():
    frames = noisy_hdr_frames(2, seed=7)
    mapper = ToneMapper(ToneSettings(adapt_s=5.0), reset_after_s=2.0)
    mapper.update(frames[0], 0)
    stats = mapper.update(frames[1] * np.float32(16), 3_000_000_000)  # 3 s later: nobody watched
    assert stats.log2_average == pytest.approx(ToneMapper().update(frames[1] * np.float32(16), 0).log2_average)


@pytest.mark.parametrize("bad", [{"key": 2.0}, {"adapt_s": -1.0}, {"white_percentile": 10.0},
                                 {"exposure_ev": float("nan")}])
def test_bad_settings_are_one_line_errors(bad):
    with pytest.raises(SveliveError, match=next(iter(bad))):
        ToneSettings(**bad)


# ----- colour -------------------------------------------------------------------------------------------

from svelive.exr import LUMA_WEIGHTS  # noqa: E402
from svelive.tonemap import KNEE, curve_constants, frame_statistics  # noqa: E402

CAMERA_TO_DISPLAY = np.array([[1.7, -0.5, -0.2], [-0.25, 1.45, -0.2], [0.05, -0.45, 1.4]]) @ np.diag([2.0, 1.0, 1.5])


def colour_reference(image: np.ndarray, matrix: np.ndarray, stats: ToneStats, settings: ToneSettings) -> np.ndarray:
    """The colour operator as documented, in float64 without tables: uint8 (H, W, 3) RGB."""
    c = image.astype(np.float64) @ matrix.T
    lum = np.maximum(c @ np.array(LUMA_WEIGHTS), 0)
    scale, inverse_white2 = (float(x) for x in curve_constants(stats, settings))
    yk = lum * scale
    gain = scale * (1 + yk * inverse_white2) / (1 + yk)
    grey = (lum * gain)[..., None]
    c = c * gain[..., None]
    hi, lo = c.max(axis=-1, keepdims=True), c.min(axis=-1, keepdims=True)
    t = np.maximum(hi - KNEE, 0) / (1 - KNEE)
    target = np.maximum(np.minimum(KNEE + (1 - KNEE) * t / (1 + t), hi), grey)
    s = np.minimum((target - grey) / np.maximum(hi - grey, 1e-30), 1)
    s = np.minimum(s, grey / np.maximum(grey - lo, 1e-30))
    return np.rint(srgb_encode(grey + s * (c - grey)) * 255).astype(np.uint8)


def colour_frame(seed: int = 0) -> np.ndarray:
    """A shipped scene in colour, seen through a warm light, in DN (float32 (256, 256, 3))."""
    scene = np.maximum(load_sample_scene("desk", rgb=True), 0)
    return (scene * np.float32([0.5, 1.0, 0.67]) * np.float32(4000 / np.percentile(scene, 99))).astype(np.float32)


def test_colour_matches_the_operator_evaluated_directly():
    image = colour_frame()
    rng = np.random.default_rng(2)
    image[:8] = (2.0 ** rng.uniform(-12, 16, (8, image.shape[1], 3))).astype(np.float32)  # far over and under range
    for settings, matrix in ((ToneSettings(), np.eye(3)), (ToneSettings(exposure_ev=3, key=0.3), CAMERA_TO_DISPLAY)):
        mapper = ToneMapper(settings)
        mapper.update(image, 0, matrix)
        out = mapper.apply(image, matrix)
        assert out.dtype == np.uint8 and out.shape == image.shape
        # the sRGB table quantises in steps of 2**-8 (0.4 %): at most one code value off
        assert np.abs(out.astype(int) - colour_reference(image, matrix, mapper.stats, settings)).max() <= 1


def test_grey_is_mapped_as_mono_and_bgr_is_rgb_reversed():
    mono = noisy_hdr_frames(1)[0]
    grey = np.repeat(mono[:, :, None], 3, axis=2)
    mapper = ToneMapper()
    mapper.update(mono, 0)
    assert mapper.update(grey, 0).log2_average == pytest.approx(ToneMapper().update(mono, 0).log2_average, abs=1e-5)
    colour = mapper.apply(grey)
    assert np.array_equal(colour[:, :, 0], colour[:, :, 1]) and np.array_equal(colour[:, :, 1], colour[:, :, 2])
    assert np.abs(colour[:, :, 0].astype(int) - mapper.apply(mono)).max() <= 1
    image = colour_frame()
    mapper.update(image, 0, CAMERA_TO_DISPLAY)
    assert np.array_equal(mapper.apply(image, CAMERA_TO_DISPLAY, bgr=True),
                          mapper.apply(image, CAMERA_TO_DISPLAY)[:, :, ::-1])


def test_statistics_of_colour_are_those_of_its_display_luminance():
    image = colour_frame()
    luminance = (image.astype(np.float64) @ CAMERA_TO_DISPLAY.T @ np.array(LUMA_WEIGHTS)).astype(np.float32)
    ours = frame_statistics(image, 99.5, CAMERA_TO_DISPLAY)
    assert ours == pytest.approx(frame_statistics(luminance, 99.5), abs=1e-4)


def test_in_range_colours_keep_their_ratios():
    image = colour_frame()
    mapper = ToneMapper(ToneSettings(exposure_ev=-2))  # darker: most pixels well inside the range
    out = mapper(image, 0)
    linear = ((out / 255.0 + 0.055) / 1.055) ** 2.4  # sRGB decoded
    inside = np.all((out > 40) & (out < 200), axis=2)
    assert inside.mean() > 0.2
    # channel ratios of the preview are those of the radiance (up to the 8-bit steps): hue and saturation kept
    for a, b in ((0, 1), (2, 1)):
        ratio = (linear[inside, a] / linear[inside, b]) / (image[inside, a] / image[inside, b])
        assert np.all(np.isfinite(ratio))
        assert np.median(np.abs(ratio - 1)) < 0.02


def test_bright_coloured_highlight_turns_white_smoothly_without_hue_flips():
    # an orange light brightening over 16 stops; the red channel leaves the display range first
    steps = 2.0 ** np.linspace(-4, 12, 400)
    ramp = (steps[:, None] * np.array([1.0, 0.45, 0.08])).astype(np.float32)[None, :, :]
    background = np.full((4, 400, 3), 1.0, np.float32)
    image = np.concatenate([background, ramp])
    out = ToneMapper(ToneSettings(adapt_s=0))(image, 0)[-1].astype(int)
    r, g, b = out.T
    assert np.all(np.diff(out, axis=0) >= 0)  # every channel only rises with the light: no posterised dips
    assert np.all((r >= g) & (g >= b))  # the hue order of orange everywhere: never magenta or green
    assert out[-1].tolist() == [255, 255, 255]  # far over range: white
    # where red reaches the top it is not clipped alone: green and blue are already rising towards it
    first_red = int(np.argmax(r == 255))
    assert g[first_red] > 200 and b[first_red] > 150


def test_negative_channels_from_a_matrix_are_desaturated_not_clipped():
    # a saturated cyan-green that a strong matrix pushes below zero in red, as a patch of a real frame
    matrix = np.array([[2.0, -1.0, 0.0], [-0.2, 1.4, -0.2], [0.0, -0.4, 1.4]])
    colour = np.array([50.0, 400.0, 300.0])
    assert (matrix @ colour)[0] < 0
    image = colour_frame()
    mapper = ToneMapper(ToneSettings(adapt_s=0))
    mapper.update(image, 0, matrix)
    image[:16, :16] = colour * 2.0 ** mapper.stats.log2_average / (matrix @ colour @ np.array(LUMA_WEIGHTS))
    out = mapper.apply(image, matrix)
    assert np.abs(out.astype(int) - colour_reference(image, matrix, mapper.stats, mapper.settings)).max() <= 1
    pixel = out[0, 0]
    assert pixel[0] <= 1  # red brought to 0 by moving towards grey ...
    linear = ((pixel / 255.0 + 0.055) / 1.055) ** 2.4
    # ... with the pixel's display luminance kept: at the log-average, the curve's display of the key
    scale, inverse_white2 = (float(x) for x in curve_constants(mapper.stats, mapper.settings))
    y = mapper.settings.key
    assert linear @ np.array(LUMA_WEIGHTS) == pytest.approx(y * (1 + y * inverse_white2) / (1 + y), rel=0.03)


def test_colour_refusals():
    mapper = ToneMapper()
    mapper.update(np.ones((4, 4), np.float32), 0)
    with pytest.raises(SveliveError, match="mono"):
        mapper.apply(np.ones((4, 4), np.float32), np.eye(3))
    with pytest.raises(SveliveError, match="3x3"):
        mapper.apply(np.ones((4, 4, 3), np.float32), np.eye(2))
    with pytest.raises(SveliveError, match=r"\(H, W, 3\)"):
        mapper.apply(np.ones((4, 4, 2), np.float32))
