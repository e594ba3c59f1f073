"""Preview tone mapping: curve correctness, no flicker on a static noisy scene, settling after a step."""

from __future__ import annotations

import numpy as np
import pytest

from svelive import Sensor
from svelive.errors import SveliveError
from svelive.pattern import Pattern
from svelive.reconstruction.single import reconstruct
from svelive.simulate import exposure_scale, load_sample_scene, simulate
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
