"""White balance (fixed, automatic with temporal smoothing), the camera matrix and the colour settings."""

from __future__ import annotations

import numpy as np
import pytest

from svelive.core.errors import SveliveError
from svelive.simulation import load_sample_scene
from svelive.whitebalance import (
    ColourSettings,
    WhiteBalance,
    WhiteBalancer,
    apply_matrix,
    estimate_white_balance,
    exr_attributes,
    output_matrix,
    parse_colour_matrix,
    parse_white_balance,
    to_output_space,
)

FRAME_NS = 33_333_333  # 30 fps
#: A warm light as the camera sees it: red strong, blue weak (multipliers that undo it: 0.5, 1, 1.6).
ILLUMINANT = np.float32([2.0, 1.0, 0.625])


def grey_world_scene(seed: int = 0, shape: tuple[int, int] = (240, 320)) -> np.ndarray:
    """Reflectances whose log-chromaticities average to grey: float32 (H, W, 3), a 10-stop range of brightness.

    Every 8x8 patch has a random brightness and a random colour symmetric about grey.
    """
    rng = np.random.default_rng(seed)
    cells = (shape[0] // 8, shape[1] // 8)
    brightness = 2.0 ** rng.uniform(-10, 0, cells)
    chroma = 2.0 ** rng.normal(0, 0.3, cells + (3,))
    chroma /= np.exp2(np.log2(chroma).mean(axis=2, keepdims=True))  # each patch's colour has grey as its log-mean
    patches = brightness[..., None] * chroma
    return np.kron(patches, np.ones((8, 8, 1))).astype(np.float32) * 4000


def with_noise(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Poisson-like noise (10 electrons per DN) and 2 DN read noise, as a reconstruction leaves it."""
    noisy = image + rng.normal(0, 1, image.shape).astype(np.float32) * np.sqrt(image / 10 + 4).astype(np.float32)
    return noisy.astype(np.float32)


def test_parse_white_balance_normalises_to_green():
    assert parse_white_balance("auto") == "auto" and parse_white_balance(" AUTO ") == "auto"
    assert parse_white_balance("2,2,3") == (1.0, 1.0, 1.5)
    assert parse_white_balance([2.1, 1, 1.6]) == (2.1, 1.0, 1.6)
    assert parse_white_balance("2 1 1.5") == (2.0, 1.0, 1.5)


@pytest.mark.parametrize("bad, words", [
    ("2,1", "expected 3 numbers"), ([1, 0, 1], "must be > 0"), ("1,-1,1", "must be > 0"),
    ("1,nan,1", "finite"), ("warm", "is not a number"), ([100, 1, 1], "within"), ("", "got nothing"),
    (None, "got nothing"), ([True, 1, 1], "is not a number"),
])
def test_bad_white_balance_is_one_line(bad, words):
    with pytest.raises(SveliveError, match=words) as info:
        parse_white_balance(bad)
    assert "\n" not in str(info.value)


def test_parse_colour_matrix_forms():
    flat = (1.6, -0.4, -0.2, -0.3, 1.5, -0.2, 0.0, -0.5, 1.5)
    assert parse_colour_matrix(flat) == flat
    assert parse_colour_matrix(np.array(flat).reshape(3, 3)) == flat
    assert parse_colour_matrix("1.6,-0.4,-0.2 / -0.3,1.5,-0.2 / 0,-0.5,1.5") == flat
    assert parse_colour_matrix(None) is None and parse_colour_matrix("none") is None and parse_colour_matrix("") is None


@pytest.mark.parametrize("bad, words", [
    ("1,0,0,0,1,0,0,0", "expected 9 numbers"), (np.eye(2), "shape"), (np.ones((3, 4)), "shape"),
    ([1, 0, 0, 0, float("inf"), 0, 0, 0, 1], "finite"), ("1,0,0,0,1,0,0,0,x", "not a number"),
    ([1e308, 0, 0, 0, 1, 0, 0, 0, 1], "within"),
])
def test_bad_colour_matrix_is_one_line(bad, words):
    with pytest.raises(SveliveError, match=words) as info:
        parse_colour_matrix(bad)
    assert "\n" not in str(info.value)


def test_colour_settings_validation():
    settings = ColourSettings(white_balance="2,1,1.5", colour_matrix=np.eye(3), output_space="REC709")
    assert settings.white_balance == (2.0, 1.0, 1.5) and settings.output_space == "rec709"
    assert settings.matrix.shape == (3, 3) and not settings.auto
    assert settings.public() == {"white_balance": [2.0, 1.0, 1.5], "colour_matrix": [1, 0, 0, 0, 1, 0, 0, 0, 1],
                                 "output_space": "rec709"}
    with pytest.raises(SveliveError, match="needs a colour matrix"):
        ColourSettings(output_space="rec709")
    with pytest.raises(SveliveError, match="camera, rec709"):
        ColourSettings(output_space="srgb")


def test_estimate_recovers_the_illuminant_of_a_grey_world_scene():
    scene = grey_world_scene()
    camera = with_noise(scene * ILLUMINANT, np.random.default_rng(1))
    estimate = estimate_white_balance(camera)
    assert estimate[1] == 1.0
    np.testing.assert_allclose(estimate * ILLUMINANT, 1.0, rtol=0.03)


def test_estimate_ignores_a_coloured_light_source_and_a_coloured_object():
    scene = grey_world_scene(seed=2)
    h, w, _ = scene.shape
    # a saturated blue lamp, far brighter than anything else (2 % of the frame), and a red object (12 %)
    scene[:h // 10, :w // 5] = np.float32([200, 400, 40000])
    scene[h // 2:h // 2 + h // 5, w // 3:w // 3 + int(0.6 * w)] *= np.float32([3.0, 0.6, 0.6])
    camera = scene * ILLUMINANT
    estimate = estimate_white_balance(camera)
    np.testing.assert_allclose(estimate * ILLUMINANT, 1.0, rtol=0.05)
    # the plain grey world (mean of every pixel) is pulled far off by them: the trimming is what holds
    plain = camera.reshape(-1, 3).mean(axis=0)
    assert abs(plain[1] / plain[2] * ILLUMINANT[2] - 1) > 0.5


def test_estimate_uses_only_valid_pixels_and_needs_enough_of_them():
    scene = grey_world_scene(seed=3)
    camera = scene * ILLUMINANT
    valid = np.ones(camera.shape[:2], bool)
    camera[:, : camera.shape[1] // 2] *= np.float32([1, 1, 8])  # invalid half with a blue cast
    valid[:, : camera.shape[1] // 2] = False
    np.testing.assert_allclose(estimate_white_balance(camera, valid) * ILLUMINANT, 1.0, rtol=0.05)
    assert estimate_white_balance(np.zeros((64, 64, 3), np.float32)) is None
    assert estimate_white_balance(camera, np.zeros(camera.shape[:2], bool)) is None


def test_auto_balancer_is_steady_on_a_static_noisy_scene_and_follows_a_change_smoothly():
    scene = grey_world_scene(seed=4)
    rng = np.random.default_rng(5)
    balancer = WhiteBalancer(ColourSettings(), adapt_s=1.0)
    history = [balancer.update(with_noise(scene * ILLUMINANT, rng), i * FRAME_NS).multipliers for i in range(30)]
    steady = np.array(history[10:])
    # after the first frames the colour does not wander: 0.5 % is below a visible cast
    assert np.all(np.abs(steady / steady.mean(axis=0) - 1) < 0.005)
    # the light turns blue: the balance moves towards the new one frame by frame, not at once
    blue = np.float32([0.5, 1.0, 2.0])
    after = [balancer.update(with_noise(scene * blue, rng), (30 + i) * FRAME_NS).multipliers for i in range(150)]
    reds = np.array([m[0] for m in after])
    assert np.all(np.diff(reds) > -0.01)  # monotonic up to noise
    assert reds[0] < 0.6  # one frame later: still close to the old 0.5
    np.testing.assert_allclose(np.array(after[-1]) * blue, 1.0, rtol=0.03)  # 5 s later: the new light


def test_gap_restarts_and_fixed_mode():
    scene = grey_world_scene(seed=6)
    balancer = WhiteBalancer(ColourSettings(), adapt_s=5.0, reset_after_s=2.0)
    balancer.update(scene * ILLUMINANT, 0)
    blue = np.float32([0.5, 1.0, 2.0])
    restarted = balancer.update(scene * blue, 3_000_000_000)  # 3 s later: nobody watched
    np.testing.assert_allclose(np.array(restarted.multipliers) * blue, 1.0, rtol=0.03)
    balancer.configure(ColourSettings(white_balance=(1.5, 1, 2)))
    fixed = balancer.update(scene * blue, 3_100_000_000)
    assert fixed.multipliers == (1.5, 1.0, 2.0) and fixed.mode == "fixed"
    assert balancer.for_frame(scene, 0).multipliers == (1.5, 1.0, 2.0)


def test_for_frame_uses_the_recent_state_else_the_frame_itself():
    scene = grey_world_scene(seed=7)
    balancer = WhiteBalancer(ColourSettings())
    assert balancer.for_frame(scene * ILLUMINANT, 0).mode == "auto"  # no state yet: the frame's own estimate
    np.testing.assert_allclose(np.array(balancer.for_frame(scene * ILLUMINANT, 0).multipliers) * ILLUMINANT, 1,
                               rtol=0.03)
    state = balancer.update(scene * ILLUMINANT, 0)
    assert balancer.for_frame(scene, FRAME_NS) is state  # recent: the preview's balance
    assert balancer.for_frame(scene, 10_000_000_000).multipliers != state.multipliers  # stale: its own


def test_output_matrix_and_spaces():
    rng = np.random.default_rng(8)
    image = rng.uniform(0, 1000, (4, 5, 3)).astype(np.float32)
    m = np.array([[1.6, -0.4, -0.2], [-0.3, 1.5, -0.2], [0.0, -0.5, 1.5]])
    wb = (2.0, 1.0, 1.5)
    expected = np.einsum("ij,hwj->hwi", m @ np.diag(wb), image)
    np.testing.assert_allclose(apply_matrix(image, output_matrix(wb, m)), expected, rtol=1e-5)
    np.testing.assert_allclose(output_matrix(wb), np.diag(wb))
    camera = ColourSettings()
    assert to_output_space(image, WhiteBalance(wb, "fixed", 0), camera) is image
    rec709 = ColourSettings(colour_matrix=m.ravel(), output_space="rec709")
    np.testing.assert_allclose(to_output_space(image, wb, rec709), expected, rtol=1e-5)
    with pytest.raises(SveliveError, match="RGB image"):
        apply_matrix(image[:, :, 0], np.eye(3))


def test_exr_attributes_say_what_the_data_is():
    wb = WhiteBalance((2.0, 1.0, 1.5), "auto", 0)
    camera = exr_attributes(wb, ColourSettings())
    assert camera["colourSpace"] == "camera" and camera["whiteBalanceApplied"] == 0
    assert camera["whiteBalanceMode"] == "auto" and "chromaticities" not in camera
    np.testing.assert_array_equal(camera["whiteBalance"], [2.0, 1.0, 1.5])
    rec709 = exr_attributes(wb, ColourSettings(colour_matrix=np.eye(3), output_space="rec709"))
    assert rec709["whiteBalanceApplied"] == 1 and rec709["colourMatrix"].shape == (3, 3)
    assert rec709["chromaticities"] == (0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290)


def test_shipped_scene_estimate_is_finite_and_bounded():
    scene = load_sample_scene("desk", rgb=True)
    estimate = estimate_white_balance(np.maximum(scene, 0))
    assert estimate is not None and np.all(np.isfinite(estimate)) and np.all((estimate > 1 / 64) & (estimate < 64))


def test_frames_between_measurements_reuse_the_last_one():
    scene = grey_world_scene(seed=9)
    balancer = WhiteBalancer(ColourSettings(), adapt_s=0.0, measure_s=0.09)  # adapt 0: each measurement taken as is
    first = balancer.update(scene * ILLUMINANT, 0)
    blue = np.float32([0.5, 1.0, 2.0])
    assert balancer.update(scene * blue, FRAME_NS) is first  # 33 ms later: not measured
    assert balancer.update(scene * blue, 2 * FRAME_NS) is first  # 67 ms
    measured = balancer.update(scene * blue, 3 * FRAME_NS)  # 100 ms: measured
    np.testing.assert_allclose(np.array(measured.multipliers) * blue, 1.0, rtol=0.03)
