"""The noise model from the data (svelive/noise/): gain and read noise estimated from SVE frames.

Simulated frames with known gain and read noise, on synthetic smooth scenes and on the shipped
crops (svelive/data), mono and colour; the stream tracker; the wiring into svelive.reconstruct.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

import svelive
from svelive import Camera, Pattern, Sensor, simulate
from svelive.calibrate.noise import fit_noise_model, noise_curve_frame
from svelive.core.camera import COLOUR_LAYOUTS
from svelive.noise import (
    EstimatorConfig,
    NoiseEstimate,
    NoiseTracker,
    cancellation_fit,
    estimate_from_frame,
    fit_line,
    joint_texture_fit,
)
from svelive.reconstruction.input import prepare
from svelive.reconstruction.single import run_method
from svelive.simulation import exposure_scale, load_sample_scene

BITS, BLACK = 12, 64
#: (full well e-, read noise DN): the bench sensor's and the corners of a wide range
MODELS = [(10_000, 2.0), (3_000, 6.0), (40_000, 0.7)]


def true_sensor(full_well: float, read_noise: float) -> Sensor:
    return Sensor(BITS, BLACK, None, full_well / (2**BITS - 1 - BLACK), read_noise)


def unknown(pattern: str, cfa: str | None = None) -> Camera:
    """The camera the estimator is given: levels only, no gain, no read noise."""
    return Camera.build(pattern, cfa, Sensor(BITS, BLACK))


def smooth_scene(n: int = 384, rgb: bool = False) -> np.ndarray:
    """A 9-stop horizontal ramp with a vertical sine: smooth at the pixel scale, float32 (n, n) or (n, n, 3)."""
    yy, xx = np.mgrid[0:n, 0:n] / n
    lum = (2.0 ** (-9 * xx) * (1 + 0.3 * np.sin(2 * np.pi * yy))).astype(np.float32)
    if not rgb:
        return lum
    return np.stack([lum * 0.8, lum, lum * (0.6 + 0.3 * yy)], axis=-1).astype(np.float32)


def frame(scene: np.ndarray, pattern: str, truth: Sensor, stops: float, cfa: str | None = None, seed: int = 1):
    p = Pattern.parse(pattern)
    return simulate(scene * np.float32(exposure_scale(scene, p, truth, stops_below_fill=stops)), p, truth,
                    cfa=cfa, seed=seed)


@pytest.mark.parametrize("full_well,read", MODELS)
@pytest.mark.parametrize("stops", [0, 5])
@pytest.mark.parametrize("pattern", ["1,4/16,64", "1/1/8/8"])
def test_smooth_scene_gain_and_read_noise_within_15_percent(pattern, stops, full_well, read):
    truth = true_sensor(full_well, read)
    est = estimate_from_frame(frame(smooth_scene(), pattern, truth, stops).raw, unknown(pattern))
    assert est.source == "estimated"
    assert est.gain == pytest.approx(truth.gain, rel=0.15)
    assert est.read_noise == pytest.approx(truth.read_noise, rel=0.15)
    # the stated uncertainty is a real one: positive, and not hiding a miss several times its size
    assert 0 < est.gain_sigma < 0.15 * est.gain
    assert abs(est.gain - truth.gain) < 4 * est.gain_sigma + 0.05 * truth.gain


@pytest.mark.parametrize("layout", ["dual-iso", "quad-bayer", "assorted-4x4"])
@pytest.mark.parametrize("full_well,read", [(10_000, 2.0), (3_000, 6.0)])
def test_colour_frames_estimated_from_same_colour_neighbours(layout, full_well, read):
    pattern, cfa = COLOUR_LAYOUTS[layout]
    truth = true_sensor(full_well, read)
    raw = frame(smooth_scene(rgb=True), pattern, truth, 0, cfa=cfa).raw
    est = estimate_from_frame(raw, unknown(pattern, cfa))
    assert est.gain == pytest.approx(truth.gain, rel=0.15)
    assert est.read_noise == pytest.approx(truth.read_noise, rel=0.15)


@pytest.mark.parametrize("name,full_well,read", [
    ("desk", 10_000, 2.0),
    # a known miss of this draw (seed 1) since issue 12.1's fifth pass: +36 % (stated 12 %). Over seeds
    # 1-10 of this crop and model, 8 of 10 are within 20 % before and after the pass (before, seed 10 read
    # +54 %); on the shipped crops' grid gain within 15 % rose from 46 % to 55 % of 288 runs (docs/noise.md)
    pytest.param("desk", 3_000, 6.0, marks=pytest.mark.xfail(strict=True, reason="known miss of one draw")),
    ("mttamwest", 3_000, 6.0)])
def test_texture_does_not_inflate_the_estimate(name, full_well, read):
    """Bright frames of the shipped crops (real texture at the pixel scale): the older single-frame
    curve (second differences of one exposure) reads the gain 30-55 % low here, i.e. the noise
    variance 1.4-2.2x high; the SVE estimate is within 20 % and the read noise within 15 %.
    (Not every crop and model gets there: docs/noise.md lists the misses.)"""
    truth = true_sensor(full_well, read)
    raw = frame(load_sample_scene(name), "1,4/16,64", truth, 0).raw
    est = estimate_from_frame(raw, unknown("1,4/16,64"))
    assert est.source == "estimated"
    assert est.gain == pytest.approx(truth.gain, rel=0.2)
    assert est.read_noise == pytest.approx(truth.read_noise, rel=0.15)
    old = fit_noise_model(noise_curve_frame(raw, "1,4/16,64", Sensor(BITS, BLACK)), "single-frame", robust=True)
    assert old.gain < 0.75 * truth.gain  # the texture the old estimate took for noise
    assert abs(np.log(est.gain / truth.gain)) < abs(np.log(old.gain / truth.gain)) / 2


@pytest.mark.parametrize("full_well,read", MODELS)
def test_desk_crop_truth_within_the_stated_uncertainty(full_well, read):
    """On the desk crop, bright and dim, the truth lies within three stated standard uncertainties
    (plus 10 % for what texture adds) of the estimate, or the estimate says it fell back to the defaults."""
    truth = true_sensor(full_well, read)
    for stops in (0, 5):
        est = estimate_from_frame(frame(load_sample_scene("desk"), "1,4/16,64", truth, stops).raw, unknown("1,4/16,64"))
        if est.source == "default":
            continue
        assert abs(est.gain - truth.gain) <= 3 * est.gain_sigma + 0.1 * truth.gain, stops
        assert abs(est.read_noise - truth.read_noise) <= 3 * est.read_noise_sigma + 0.1 * truth.read_noise, stops


@pytest.mark.parametrize("full_well,read", MODELS)
def test_read_noise_on_shipped_crops_bright_and_dim(full_well, read):
    truth = true_sensor(full_well, read)
    scene = load_sample_scene("desk")
    for stops in (0, 5):
        est = estimate_from_frame(frame(scene, "1,4/16,64", truth, stops).raw, unknown("1,4/16,64"))
        assert est.read_noise == pytest.approx(truth.read_noise, rel=0.15), stops


def test_given_values_are_kept_and_held_fixed():
    truth = true_sensor(10_000, 2.0)
    raw = frame(smooth_scene(), "1,4/16,64", truth, 0).raw
    given = estimate_from_frame(raw, Camera.build("1,4/16,64", None, truth))
    assert (given.gain, given.read_noise, given.source) == (truth.gain, truth.read_noise, "given")
    half = Camera.build("1,4/16,64", None, Sensor(BITS, BLACK, None, truth.gain, None))
    est = estimate_from_frame(raw, half)
    assert est.gain == truth.gain and est.gain_sigma == 0.0
    assert est.read_noise == pytest.approx(truth.read_noise, rel=0.1)
    assert est.apply(half.sensor).gain == truth.gain


def test_blank_or_saturated_frame_falls_back_to_the_defaults():
    for value in (BLACK, 2**BITS - 1):
        est = estimate_from_frame(np.full((64, 64), value, np.uint16), unknown("1,4/16,64"))
        sensor = Sensor(BITS, BLACK)
        assert est.source == "default"
        assert est.gain == pytest.approx(sensor.effective_gain)
        assert est.read_noise == pytest.approx(sensor.effective_read_noise)
        # the frame told nothing: the uncertainty is the prior's, wide enough to cover any real sensor
        assert est.gain_sigma == pytest.approx(np.log(4) * est.gain)
        assert est.read_noise_sigma == pytest.approx(np.log(4) * est.read_noise)


def test_report_forms_are_json_safe():
    est = NoiseEstimate(2.5, 1.2, float("inf"), None, 10, "estimated")
    data = json.loads(json.dumps(est.to_dict()))
    assert data == {"gain": 2.5, "read_noise": 1.2, "gain_sigma": None, "read_noise_sigma": None,
                    "samples": 10, "source": "estimated"}
    attrs = NoiseEstimate(2.5, 1.2, 0.1, 0.05, 10, "estimated").attributes()
    assert attrs == {"noiseGain": 2.5, "noiseReadNoise": 1.2, "noiseSource": "estimated",
                     "noiseGainSigma": 0.1, "noiseReadNoiseSigma": 0.05}
    assert "e-/DN" in est.describe()


def test_reconstruct_without_noise_model_uses_the_estimate():
    truth = true_sensor(3_000, 6.0)
    raw = frame(load_sample_scene("desk"), "1,4/16,64", truth, 5).raw
    est = estimate_from_frame(raw, unknown("1,4/16,64"))
    auto = svelive.reconstruct(raw, "1,4/16,64", black_level=BLACK, white_level=2**BITS - 1)
    explicit = svelive.reconstruct(raw, "1,4/16,64", black_level=BLACK, white_level=2**BITS - 1,
                                   gain=est.gain, read_noise=est.read_noise)
    default = svelive.reconstruct(raw, "1,4/16,64", black_level=BLACK, white_level=2**BITS - 1, noise="default")
    assert np.array_equal(auto, explicit)
    assert not np.array_equal(auto, default)
    with pytest.raises(svelive.SveliveError, match="noise must be"):
        svelive.reconstruct(raw, "1,4/16,64", noise="guess")


def test_given_noise_model_reconstructs_exactly_as_before():
    truth = true_sensor(10_000, 2.0)
    raw = frame(load_sample_scene("cannon"), "1,4/16,64", truth, 0).raw
    camera = Camera.build("1,4/16,64", None, truth)
    direct = run_method(prepare(raw, camera)).image
    assert np.array_equal(svelive.reconstruct(raw, camera), direct)


def test_tracker_removes_texture_with_static_pixels():
    """Temporal differences of a static scene cancel its texture: after a few frames the tracker is
    within 10 % on the textured crop where one frame alone reads the gain low."""
    truth = true_sensor(10_000, 2.0)
    scene = load_sample_scene("mttamwest")
    camera = unknown("1,4/16,64")
    tracker = NoiseTracker()
    assert tracker.estimate is None
    for seed in range(6):
        raw = frame(scene, "1,4/16,64", truth, 0, seed=seed).raw
        est = tracker.update(raw, camera, np.ones(raw.shape, bool))
    assert est.source == "estimated"
    assert est.gain == pytest.approx(truth.gain, rel=0.1)
    assert est.read_noise == pytest.approx(truth.read_noise, rel=0.1)
    # a new camera starts over
    other = tracker.update(raw, unknown("1,2/4,8"))
    assert other.samples < est.samples


def covered(estimate: float, sigma: float, truth: float) -> bool:
    """The truth within two stated standard uncertainties, counted in log space (relative): a gain's
    uncertainty is a factor (the prior is log-normal), so ``sigma / estimate`` is its log-sigma."""
    return abs(np.log(truth / estimate)) <= 2 * sigma / estimate


@pytest.mark.parametrize("stops", [5, 7])
def test_gain_one_frame_cannot_tell_is_declared_unknown_not_wrong(stops):
    """A 40 000 e- well with 6 DN read noise: shot noise exceeds the read noise only above about
    360 DN, which a dim frame hardly reaches, so one frame cannot tell the gain. The estimate must
    say so through its uncertainty (at least 50 %, the truth within two of it) rather than be
    confidently wrong; the read noise it can tell."""
    truth = true_sensor(40_000, 6.0)
    est = estimate_from_frame(frame(load_sample_scene("desk"), "1,4/16,64", truth, stops).raw, unknown("1,4/16,64"))
    assert est.read_noise == pytest.approx(truth.read_noise, rel=0.15)
    assert est.gain_sigma >= 0.5 * est.gain
    assert covered(est.gain, est.gain_sigma, truth.gain)


@pytest.mark.parametrize("full_well,read", [(20_000, 1.2), (40_000, 0.7)])
def test_two_static_frames_give_the_gain_one_textured_frame_misses(full_well, read):
    """On the textured mttamwest crop, bright, one frame reads the gain more than 15 % low (texture
    that passes the flatness tests grows with the signal like shot noise); the difference of two
    static frames removes the texture, and the tracker is within 15 % after the second frame."""
    truth = true_sensor(full_well, read)
    scene = load_sample_scene("mttamwest")
    camera = unknown("1,4/16,64")
    first, second = (frame(scene, "1,4/16,64", truth, 0, seed=seed).raw for seed in (1, 2))
    one = estimate_from_frame(first, camera)
    assert abs(one.gain / truth.gain - 1) > 0.15
    tracker = NoiseTracker()
    tracker.update(first, camera)
    two = tracker.update(second, camera, np.ones(first.shape, bool))
    assert two.gain == pytest.approx(truth.gain, rel=0.15)
    assert covered(two.gain, two.gain_sigma, truth.gain)


def test_calibrate_single_frame_does_not_state_a_default_gain_as_exact():
    """A black frame (no signal range) gives the read noise but not the gain: ``svelive calibrate noise``
    keeps the default gain and must state the prior's uncertainty for it, not 0."""
    from svelive.calibrate.noise import calibrate_noise

    truth = true_sensor(10_000, 2.0)
    raw = simulate(np.zeros((256, 256), np.float32), Pattern.parse("1,4/16,64"), truth, seed=1).raw
    model = calibrate_noise([raw], Sensor(BITS, BLACK), "1,4/16,64")
    assert model.read_noise == pytest.approx(truth.read_noise, rel=0.15)
    assert model.gain_sigma == pytest.approx(np.log(4) * model.gain)


# ----- texture cancelled across exposures (issue 12.1, third pass) ------------------------------------


def textured_scene(n: int = 768, contrast: float = 0.1, seed: int = 0) -> np.ndarray:
    """The smooth ramp times a pixel-scale texture: log-normal, blurred by a [1, 2, 1] kernel twice along
    each axis (correlated over a few pixels, like fabric or foliage), float32 (n, n)."""
    rng = np.random.default_rng(seed)
    field = rng.standard_normal((n, n))
    kernel = np.array([0.25, 0.5, 0.25])
    for axis in (0, 1, 0, 1):
        field = np.apply_along_axis(lambda v: np.convolve(v, kernel, mode="same"), axis, field)
    field *= contrast / field.std()
    return (smooth_scene(n) * np.exp(field)).astype(np.float32)


@pytest.mark.parametrize("pattern", ["1,4/16,64", "1,2/4,8", "1/1/8/8"])
@pytest.mark.parametrize("full_well,read", [(40_000, 0.7), (3_000, 6.0)])
def test_texture_cancelled_across_exposures(pattern, full_well, read):
    """Texture that passes the flatness tests grows with the signal like shot noise, so the residual fit
    alone reads the gain low on a textured scene; residuals of one geometry at two base exposures see
    the texture scaled by the exposure squared and shot noise by the exposure, and the joint fit
    removes it: the gain within 15 %, the truth within two stated sigma (log), the read noise within 15 %."""
    truth = true_sensor(full_well, read)
    raw = frame(textured_scene(), pattern, truth, 0).raw
    residual_only = estimate_from_frame(raw, unknown(pattern), config=EstimatorConfig(cancellation=False))
    est = estimate_from_frame(raw, unknown(pattern))
    assert est.source == "estimated"
    assert est.gain == pytest.approx(truth.gain, rel=0.15)
    assert abs(math.log(est.gain / truth.gain)) <= 2 * est.gain_sigma / est.gain
    assert est.read_noise == pytest.approx(truth.read_noise, rel=0.15)
    if full_well == 40_000:  # where texture dominates the shot noise, the residual fit alone reads low
        assert residual_only.gain < 0.85 * truth.gain


def test_joint_texture_fit_separates_texture_from_shot_noise():
    """Noise-free bins of three geometries x six levels at base exposures 1 and 16: a texture per group
    (growing with the level, as a contrast does) on top of ``t / g + R``. The joint fit returns the line
    exactly; a line through the same bins without the texture term reads the slope (1 / gain) high."""
    slope, intercept = 1 / 2.5, 4.2
    gid, t, c, u = [], [], [], []
    for group in range(18):
        level = 2.0 ** (group % 6)
        texture = 0.05 * level * level * (1 + group // 6)
        for e in (1.0, 16.0):
            gid.append(group)
            t.append(e * level * 1.25)
            c.append(e * e / 1.0625)
            u.append(slope * t[-1] + intercept + c[-1] * texture)
    gid, t, c, u = np.array(gid), np.array(t), np.array(c), np.array(u)
    n = np.full(u.size, 500)
    fit = joint_texture_fit(gid, t, c, u, n)
    assert fit.slope == pytest.approx(slope, rel=1e-6) and fit.intercept == pytest.approx(intercept, rel=1e-6)
    plain = fit_line(t, u, n, outlier_tolerance=10.0)
    assert plain.slope > 1.5 * slope
    held = joint_texture_fit(gid, t, c, u, n, intercept=intercept)
    assert held.slope == pytest.approx(slope, rel=1e-6) and held.intercept == intercept


def test_cancellation_needs_one_geometry_at_two_base_exposures():
    """One exposure everywhere: residuals of one geometry have one base exposure, so texture cannot be
    told from shot noise and there is no joint fit; 1,4/16,64 pairs its 1 and 16 pixels by geometry
    (horizontal neighbours at 4 times the exposure)."""
    truth = true_sensor(3_000, 6.0)
    for pattern, expected in (("1,1/1,1", False), ("1,4/16,64", True)):
        raw = frame(smooth_scene(), pattern, truth, 0).raw
        fit = cancellation_fit(raw, float(BLACK), -float(BLACK), unknown(pattern))
        assert (fit is not None) == expected, pattern


def test_texture_cancellation_holds_a_given_read_noise():
    """A datasheet read noise is kept and held fixed in the joint fit too; the gain still comes out of the
    textured frame within 15 %, and the samples counted are the joint fit's residuals."""
    truth = true_sensor(40_000, 0.7)
    raw = frame(textured_scene(), "1,2/4,8", truth, 0).raw
    est = estimate_from_frame(raw, Camera.build("1,2/4,8", None, Sensor(BITS, BLACK, None, None, truth.read_noise)))
    assert est.read_noise == truth.read_noise and est.read_noise_sigma == 0.0
    assert est.gain == pytest.approx(truth.gain, rel=0.15)
    residual_only = estimate_from_frame(raw, unknown("1,2/4,8"), config=EstimatorConfig(cancellation=False))
    assert est.samples > residual_only.samples


def test_tracker_without_static_pixels_cancels_texture_too():
    """A moving camera gives the tracker no static pixels, so it has only single-frame evidence: it takes
    the recent frames' texture-cancelled fits as estimate_from_frame does, and the gain of a textured scene
    comes out within 15 % where the residual samples alone read it low."""
    truth = true_sensor(40_000, 0.7)
    scene = textured_scene()
    tracker, residual_only = NoiseTracker(), NoiseTracker(config=EstimatorConfig(cancellation=False))
    for seed in (1, 2):
        raw = frame(scene, "1/1/8/8", truth, 0, seed=seed).raw
        est = tracker.update(raw, unknown("1/1/8/8"))
        old = residual_only.update(raw, unknown("1/1/8/8"))
    assert est.gain == pytest.approx(truth.gain, rel=0.15)
    assert covered(est.gain, est.gain_sigma, truth.gain)
    assert old.gain < 0.85 * truth.gain


@pytest.mark.parametrize("pattern,full_well,read,seed", [("1,4/16,64", 10_000, 2.0, 0), ("1/1/8/8", 40_000, 0.7, 0),
                                                         ("1/1/8/8", 20_000, 1.2, 1)])
def test_heavy_texture_gain_uncertainty_covers_the_truth(pattern, full_well, read, seed):
    """A texture of 30 % contrast: the joint fit's bins are correlated (a cell's residuals share readings,
    neighbouring cells share texture, and the two exposures of a geometry see texture that differs
    over the frame), which its own covariance ignores; the delete-one-band jackknife does not. The
    gain may miss (texture left after the selection reads it low), but the truth stays within two
    stated sigma (log). Without the jackknife these three frames state 12-20 % and miss by 23-37 %."""
    truth = true_sensor(full_well, read)
    raw = frame(textured_scene(512, 0.3, seed), pattern, truth, 0).raw
    est = estimate_from_frame(raw, unknown(pattern))
    assert est.source == "estimated"
    assert abs(math.log(est.gain / truth.gain)) <= 2 * est.gain_sigma / est.gain


def test_cells_as_flat_as_noise_are_all_kept():
    """On the smooth scene (no texture) most blocks are as flat as noise: the joint fit keeps their cells
    (before issue 12.1's fifth pass only the flattest quarter of every bin), so it rests on about twice
    as many residuals or more."""
    truth = true_sensor(10_000, 2.0)
    raw = frame(smooth_scene(512), "1/1/8/8", truth, 0).raw
    camera = unknown("1/1/8/8")
    quarter = cancellation_fit(raw, float(BLACK), -float(BLACK), camera, EstimatorConfig(cancel_flat=False))
    flat = cancellation_fit(raw, float(BLACK), -float(BLACK), camera)
    assert quarter is not None and flat is not None
    assert flat.bins_n.sum() >= 2 * quarter.bins_n.sum()


@pytest.mark.parametrize("seed", [0, 1])
def test_textured_scene_gain_within_15_percent_everywhere(seed):
    """A texture of 10 % contrast, bright frames, every pattern and four noise models: with the cells of
    blocks as flat as noise kept too, the joint fit's bins are less noisy and every gain is within 15 %
    (keeping the flattest quarter alone, one of these 24 frames read the gain 25 % low)."""
    scene = textured_scene(512, 0.1, seed)
    for pattern in ("1,4/16,64", "1,2/4,8", "1/1/8/8"):
        for full_well, read in ((10_000, 2.0), (40_000, 0.7), (20_000, 1.2), (3_000, 6.0)):
            truth = true_sensor(full_well, read)
            est = estimate_from_frame(frame(scene, pattern, truth, 0, seed=seed + 1).raw, unknown(pattern))
            assert est.gain == pytest.approx(truth.gain, rel=0.15), (pattern, full_well, read)


def test_jackknife_only_widens_the_joint_fit():
    """The jackknife leaves the joint fit's line as it is and never narrows its uncertainty."""
    truth = true_sensor(20_000, 1.2)
    raw = frame(textured_scene(512, 0.1, 0), "1/1/8/8", truth, 0).raw
    camera = unknown("1/1/8/8")
    plain = cancellation_fit(raw, float(BLACK), -float(BLACK), camera, EstimatorConfig(cancel_jackknife=0))
    jack = cancellation_fit(raw, float(BLACK), -float(BLACK), camera)
    assert plain is not None and jack is not None
    assert jack.slope == plain.slope and jack.intercept == plain.intercept
    assert np.all(np.diag(jack.cov) >= np.diag(plain.cov))


@pytest.mark.parametrize("frames", [2, 3])
def test_static_frames_read_a_low_read_noise_without_bias(frames):
    """3 000 e- with 0.7 DN read noise: shot noise of a few electrons, heavier-tailed than a Gaussian,
    swamps the read noise from 1 DN up. Grouping two frames' differences by their own noisy mean and a
    3-sigma clip with the Gaussian correction read the read noise 10-27 % high; grouped by values whose
    noise is independent of theirs (same-exposure neighbours for a pair, the third frame for three) and
    clipped only for gross outliers, the tracker is within 4 % of gain and read noise on a smooth scene
    whose dark half crowds the bottom of the range (the case that makes it hard)."""
    truth = true_sensor(3_000, 0.7)
    camera = unknown("1/1/8/8")
    scene = smooth_scene(512)
    raws = [frame(scene, "1/1/8/8", truth, 5, seed=seed).raw for seed in (11, 12, 13)[:frames]]
    tracker = NoiseTracker(temporal_samples_per_frame=10**6)  # every pixel: a bias, not the sampling, decides
    tracker.update(raws[0], camera)
    static = np.ones(raws[0].shape, bool)
    for raw in raws[1:]:
        est = tracker.update(raw, camera, static)
    assert est.source == "estimated"
    assert est.read_noise == pytest.approx(truth.read_noise, rel=0.04)
    assert est.gain == pytest.approx(truth.gain, rel=0.04)
    assert covered(est.read_noise, est.read_noise_sigma, truth.read_noise)


@pytest.mark.parametrize("three", [False, True])
def test_temporal_samples_group_means_follow_the_noise_line_exactly(three):
    """The group means of temporal samples lie on t / gain + R at every signal, also at a few
    electrons (plain means, no clip): for a pair grouped by same-exposure neighbours, for three frames
    by the third."""
    from svelive.noise import QUANTISATION_VARIANCE, temporal_samples, triple_samples

    truth = true_sensor(3_000, 0.7)
    scene = smooth_scene(512)
    sig = [frame(scene, "1/1/8/8", truth, 5, seed=seed).raw.astype(np.float32) - BLACK for seed in (21, 22, 23)]
    model = (1 / truth.gain, truth.read_noise**2 + QUANTISATION_VARIANCE)
    if three:
        samples = triple_samples(*sig, None, -BLACK, truth.white_level - BLACK, model, max_samples=10**6)
    else:
        samples = temporal_samples(*sig[:2], None, -BLACK, truth.white_level - BLACK, model, max_samples=10**6,
                                   period=(4, 1))
    for lo, hi in ((0.5, 2), (2, 5), (5, 20), (20, 200)):
        sel = (samples.t >= lo) & (samples.t < hi)
        assert sel.sum() > 5000
        expected = np.mean(samples.t[sel]) / truth.gain + model[1]
        assert np.mean(samples.u[sel]) == pytest.approx(expected, rel=0.03), (lo, hi)


def test_temporal_samples_leave_the_callers_static_mask_alone():
    """The samplers drop pixels from their own copy of the static mask, never from the caller's (the
    tracker keeps the mask it was given to relate the next frame)."""
    from svelive.noise import QUANTISATION_VARIANCE, temporal_samples, triple_samples

    truth = true_sensor(10_000, 2.0)
    sig = [frame(smooth_scene(128), "1/1/8/8", truth, 0, seed=seed).raw.astype(np.float32) - BLACK
           for seed in (1, 2, 3)]
    model = (1 / truth.gain, truth.read_noise**2 + QUANTISATION_VARIANCE)
    static = np.ones(sig[0].shape, bool)
    for samples in (triple_samples(*sig, static, -BLACK, 0.5 * (truth.white_level - BLACK), model),
                    temporal_samples(*sig[:2], static, -BLACK, 0.5 * (truth.white_level - BLACK), model,
                                     period=(4, 1))):
        assert 0 < samples.size < static.size  # the half-range clip level dropped some pixels
    assert static.all()


def test_joint_fit_profiles_texture_out_exactly():
    """joint_texture_fit profiles the texture unknowns out group by group: its line and covariance are
    those of the weighted least squares with one texture column per group, written out here (weights
    as the fit's first pass: the bins' own values, no texture term; mismatch 0 keeps them there)."""
    rng = np.random.default_rng(3)
    groups, per = 12, 2
    gid = np.repeat(np.arange(groups), per)
    c = np.tile([1.0 / 3.0, 256.0 / 3.0], groups)  # texture as the base exposure squared (1 and 16)
    t = np.tile([1.0, 16.0], groups) * np.repeat(rng.uniform(5, 200, groups), per)  # shot noise as it
    d = np.repeat(rng.uniform(-0.05, 0.3, groups), per)
    n = rng.integers(200, 2000, gid.size)
    truth = t / 2.5 + 4.1 + c * d
    u = truth * (1 + rng.normal(0, 1, gid.size) * np.sqrt(2.0 / n))
    fit = joint_texture_fit(gid, t, c, u, n, mismatch=0.0)
    assert fit is not None
    # the same pass written out: weights 1 / (2 m^2 / n) with m the fitted value, iterated as the fit does
    design = np.column_stack([t, np.ones_like(t), np.zeros((u.size, groups))])
    design[np.arange(u.size), 2 + gid] = c
    fitted = np.maximum(u, 1 / 12)
    for _ in range(6):
        w = 1.0 / np.sqrt(2.0 * fitted * fitted / n)
        sol, *_ = np.linalg.lstsq(design * w[:, None], u * w, rcond=None)
        fitted = np.maximum(design @ sol, 1 / 12)
    resid = (u - design @ sol) * w
    chi2 = max(float(resid @ resid) / (u.size - design.shape[1]), 1.0)
    cov = np.linalg.pinv((design * w[:, None]).T @ (design * w[:, None]))[:2, :2] * chi2
    assert fit.slope == pytest.approx(sol[0], rel=1e-9) and fit.intercept == pytest.approx(sol[1], rel=1e-9)
    np.testing.assert_allclose(fit.cov, cov, rtol=1e-8)


def _cells(rng: np.random.Generator, symmetric: bool, excess: float = 0.0):
    """Synthetic selected cells of one geometry at base exposures 1 and 8 (gain 2.5, R 4.1, texture of
    2 % contrast): squared residuals with the expected value the joint fit models; ``excess`` adds
    variance growing with the signal to the lower base exposure's residuals only (a gradient that the
    two base exposures' rows see differently)."""
    from svelive.noise.cancellation import _CancellationSamples
    n = 6000
    level = rng.uniform(5, 300, n)
    e = np.array([1.0, 8.0])
    t = e[:, None] * level[None, :]
    c = e * e / 2
    mean = t / 2.5 + 4.1 + c[:, None] * (0.02 * level[None, :]) ** 2
    mean[0] += excess * t[0]
    u = mean * rng.chisquare(1, mean.shape)
    return _CancellationSamples(np.log(8 * level + 2), u, t, c, rng.integers(0, 16, n), symmetric)


def test_one_sided_geometries_kept_unless_they_bias_the_joint_fit():
    """Where the nearest ring has symmetric and one-sided geometries (1/1/8/8), the joint fit of the
    symmetric ones alone replaces the fit of all of them only where the two disagree beyond two of its
    standard deviations: one-sided residuals keep the scene's gradient (a bias more data does not
    shrink), but small frames need their residuals."""
    from svelive.noise.cancellation import _cancellation_table, _without_gradient_bias
    config = EstimatorConfig()
    fixed = {"slope": None, "intercept": None}
    for excess, biased in ((0.0, False), (0.3, True)):
        rng = np.random.default_rng(5)
        parts = [_cells(rng, True), _cells(rng, False, excess), _cells(rng, False, excess)]
        every = joint_texture_fit(*_cancellation_table(parts, config), **fixed)
        sym = joint_texture_fit(*_cancellation_table(parts[:1], config), **fixed)
        taken = _without_gradient_bias(every, parts, fixed, config)
        if biased:
            assert 1 / every.slope < 0.85 * 2.5 and taken.slope == sym.slope
            assert 1 / taken.slope == pytest.approx(2.5, rel=0.15)
        else:
            assert taken is every and 1 / every.slope == pytest.approx(2.5, rel=0.1)
    lone = [_cells(np.random.default_rng(6), True)]
    fit = joint_texture_fit(*_cancellation_table(lone, config), **fixed)
    assert _without_gradient_bias(fit, lone, fixed, config) is fit


def test_an_imprecise_joint_fit_is_taken_where_the_residual_fit_is_biased():
    """The joint fit is taken beyond cancel_max_sigma where the residual fit's slope lies more than two
    of the joint fit's standard deviations above it (texture biases the residual fit that way only), or
    where there is no residual fit; not where the residual fit is within reach of it."""
    from svelive.noise import LineFit
    from svelive.noise.frame import _preferred

    def line(slope: float, sd: float, fixed: bool = False) -> LineFit:
        return LineFit(slope, 4.0, np.diag([sd * sd, 0.01]), np.zeros(0), np.zeros(0), np.zeros(0),
                       np.zeros(0, bool), fixed)

    config = EstimatorConfig()
    joint = line(0.10, 0.07)  # 70 % relative: beyond cancel_max_sigma
    steep = line(0.40, 0.10)
    near = line(0.20, 0.05)
    assert _preferred(steep, joint, config) is joint
    assert _preferred(near, joint, config) is near
    assert _preferred(None, joint, config) is joint
    assert _preferred(line(0.40, 0.0, fixed=True), joint, config).fixed_slope
    assert _preferred(steep, joint, EstimatorConfig(cancel_when_biased=False)) is steep


def _live_runs(tracker: NoiseTracker, raws: list[np.ndarray], camera: Camera, fit_each_frame: bool,
               static_from: int = 0) -> list[NoiseEstimate]:
    """Runs of three frames fed as the live service's noise stage does (the first without a static mask,
    the next two with every pixel static; runs before ``static_from`` without any mask: a moving camera),
    the estimate after each run; ``fit_each_frame``: :meth:`NoiseTracker.update` on every frame, else
    :meth:`NoiseTracker.add` three times and one :meth:`NoiseTracker.fit`."""
    static = np.ones(raws[0].shape, bool)
    out = []
    for r in range(len(raws) // 3):
        for j, raw in enumerate(raws[3 * r:3 * r + 3]):
            mask = static if j and r >= static_from else None
            if fit_each_frame:
                tracker.update(raw, camera, mask)
            else:
                tracker.add(raw, camera, mask)
        out.append(tracker.estimate if fit_each_frame else tracker.fit())
    return out


@pytest.mark.parametrize("static_from", [0, 1])
def test_a_run_fitted_once_gives_the_estimate_of_a_fit_per_frame_to_the_bit(static_from):
    """Adding a run's frames and fitting once gives, after every run, the very estimate (every field
    equal, no tolerance) that fitting after every frame gives: also in the first runs, where the pool
    changes with every frame and the samples of the next frame are clipped by the fit of the ones
    before, and after a run without static pixels (texture-cancelled fits)."""
    truth = true_sensor(3_000, 2.0)
    camera = unknown("1,4/16,64")
    scene = load_sample_scene("mttamwest")[:192, :256]
    raws = [frame(scene, "1,4/16,64", truth, 2, seed=seed).raw for seed in range(12)]
    each = _live_runs(NoiseTracker(temporal_enough=60_000), raws, camera, True, static_from)
    once = _live_runs(NoiseTracker(temporal_enough=60_000), raws, camera, False, static_from)
    assert [e.source for e in each] == ["estimated"] * 4
    assert once == each
    assert len({(e.gain, e.samples) for e in once}) == 4  # every run moved it: the comparison compares


def test_a_tracker_at_rest_between_runs_keeps_no_frame_and_estimates_the_same():
    """A stream's tracker rests after each run (``NoiseTracker.rest``: its frames dropped, 20 MiB at 1920x1200,
    a digest of the last one kept): the estimates after every run are those of a tracker that kept its frames,
    to the bit, and the last frame delivered again after the rest still adds nothing."""
    truth = true_sensor(3_000, 2.0)
    camera = unknown("1,4/16,64")
    scene = load_sample_scene("mttamwest")[:192, :256]
    raws = [frame(scene, "1,4/16,64", truth, 2, seed=seed).raw for seed in range(9)]
    # (every frame's own samples pooled too: a frame added shows in the pool)
    kept, rested = NoiseTracker(temporal_enough=10**9), NoiseTracker(temporal_enough=10**9)
    static = np.ones(raws[0].shape, bool)
    for r in range(3):
        for j, raw in enumerate(raws[3 * r:3 * r + 3]):
            for tracker in (kept, rested):
                tracker.add(raw, camera, static if j else None)
        rested.rest()
        assert rested._previous is None and rested._before_previous is None and rested._previous_static is None
        assert kept._previous is not None
        assert rested.fit() == kept.fit()
    pooled = len(rested._frame_parts)
    for tracker in (kept, rested):
        tracker.add(raws[8].copy(), camera, None)  # the last frame again: nothing added
    assert len(rested._frame_parts) == len(kept._frame_parts) == pooled
    assert rested._previous is None  # (nor kept: the next frame is compared with the digest still)
    for tracker in (kept, rested):
        tracker.add(raws[0], camera, None)  # a new frame is
    assert len(rested._frame_parts) == pooled + 1 and rested.fit() == kept.fit()


def test_the_pool_is_fitted_once_per_run(monkeypatch):
    """Once three frames' samples suffice (here one run's: a small frame), the pool does not change
    between a run's first two frames and the run before, so a run costs one fit of the pool, however
    the frames are given."""
    import svelive.noise.tracker as noise

    calls = []

    def counted(*args, **kwargs):
        calls.append(1)
        return fit_line(*args, **kwargs)

    truth = true_sensor(10_000, 2.0)
    camera = unknown("1,2/4,8")
    raws = [frame(smooth_scene(256), "1,2/4,8", truth, 0, seed=seed).raw for seed in range(9)]
    for fit_each_frame in (True, False):
        tracker = NoiseTracker(temporal_enough=4_000)
        _live_runs(tracker, raws[:6], camera, fit_each_frame)
        monkeypatch.setattr(noise, "fit_line", counted)
        calls.clear()
        _live_runs(tracker, raws[6:], camera, fit_each_frame)
        monkeypatch.setattr(noise, "fit_line", fit_line)
        assert len(calls) == 1, fit_each_frame


def test_three_frames_keep_the_few_dark_pixels_of_a_bright_scene():
    """The samples of three frames are spread over signal strata by the third frame's value, not
    strided over the frame: the dark strip of a bright scene (3 % of the pixels, where the read noise
    shows) keeps nearly all its pixels within the budget, where a frame-wide stride kept one in
    eleven; and the means there still follow the noise line (the choice sees neither difference)."""
    from svelive.noise import QUANTISATION_VARIANCE, triple_samples

    truth = true_sensor(10_000, 2.0)
    radiance = np.full((256, 256), 40.0, np.float32)
    radiance[:, :8] = 0.5  # 0.5 and 4 DN under 1/1/8/8; the rest 40 and 320 DN
    sig = [simulate(radiance, "1/1/8/8", truth, seed=seed).raw.astype(np.float32) - BLACK for seed in (4, 5, 6)]
    model = (1 / truth.gain, truth.read_noise**2 + QUANTISATION_VARIANCE)
    samples = triple_samples(*sig, np.ones(radiance.shape, bool), -BLACK, truth.white_level - BLACK, model,
                             max_samples=8_000)
    dark = samples.t < 15
    assert samples.size <= 8_000
    assert dark.sum() >= 0.9 * 8 * 256
    expected = np.mean(samples.t[dark]) / truth.gain + model[1]
    assert np.mean(samples.u[dark]) == pytest.approx(expected, rel=0.1)


def test_whole_dn_readings_are_chosen_as_per_pixel():
    """The table of whole-DN values that chooses three frames' pixels gives what computing the clip
    test and the stratum for every pixel gives (a non-integer signal takes that path)."""
    from svelive.noise.stats import _bin_index
    from svelive.noise.temporal import _clear_of_clipping, _clear_strata

    x = np.round(np.random.default_rng(1).gamma(1.0, 300.0, 100_000)).astype(np.float32) - 5
    candidates = np.arange(x.size)
    model = (0.4, 4.0)
    table = _clear_strata(x, np.ones(x.size, bool), 1.01, -2.0, 2000.0, model, 24)
    c = x.astype(np.float64) * 1.01
    keep = _clear_of_clipping(c, -2.0, 2000.0, model)
    assert 0 < keep.sum() < x.size
    assert np.array_equal(table[0], candidates[keep])
    assert np.array_equal(table[1], _bin_index(c[keep], 24)[0])
    per_pixel = _clear_strata(x + np.float32(0.25), None, 1.01, -2.0, 2000.0, model, 24)
    assert per_pixel[1].dtype == np.uint8 and per_pixel[1].max() == 23


def test_whole_dn_readings_are_chosen_alike_in_any_chunks():
    """Whole-DN readings are read chunk by chunk (the live stream's peak memory): any chunk size, chunks that
    the mask leaves empty included, chooses the same positions and strata as one chunk of the whole frame,
    which are those of the per-pixel clip test and strata."""
    from svelive.noise.stats import _bin_index
    from svelive.noise.temporal import _clear_of_clipping, _clear_strata

    rng = np.random.default_rng(2)
    x = np.round(rng.gamma(1.0, 300.0, 100_000)).astype(np.float32) - 5
    mask = rng.random(x.size) < 0.7
    mask[10_000:20_000] = False
    model = (0.4, 4.0)
    whole = _clear_strata(x, mask, 1.01, -2.0, 2000.0, model, 24, chunk=x.size)
    c = x[mask].astype(np.float64) * 1.01
    keep = _clear_of_clipping(c, -2.0, 2000.0, model)
    assert np.array_equal(whole[0], np.flatnonzero(mask)[keep])
    assert np.array_equal(whole[1], _bin_index(c[keep], 24)[0])
    for chunk in (999, 4096, 10_000, 33_333):
        chosen = _clear_strata(x, mask, 1.01, -2.0, 2000.0, model, 24, chunk=chunk)
        assert chosen[0].dtype == np.int32 and chosen[1].dtype == np.uint8
        assert np.array_equal(chosen[0], whole[0]) and np.array_equal(chosen[1], whole[1]), chunk


def test_three_frames_bright_end_of_a_dim_frame_is_not_inflated():
    """The brightness ratio that removes flicker is taken over every static pixel: from a subset, its
    own noise (a dim frame's sums are mostly read noise) adds (1 - k)^2 s^2 to every difference, nothing
    in the dark and a sizeable share at the bright end, where the gain is read (40 000 e- / 6 DN: the
    tracker read the gain 20 % low on a dim real scene after 16 runs). Here 1 % of the pixels at 400 DN
    beside a 2 DN dark: over eight independent triples their mean square difference is the noise line's."""
    from svelive.noise import QUANTISATION_VARIANCE, triple_samples

    truth = true_sensor(40_000, 6.0)
    radiance = np.full((512, 512), 2.0, np.float32)
    radiance[:26, :100] = 400.0
    static = np.ones(radiance.shape, bool)
    model = (1 / truth.gain, truth.read_noise**2 + QUANTISATION_VARIANCE)
    parts = []
    for run in range(8):
        sig = [simulate(radiance, "1", truth, seed=100 + 3 * run + j).raw.astype(np.float32) - BLACK for j in range(3)]
        parts.append(triple_samples(*sig, static, -BLACK, truth.white_level - BLACK, model, max_samples=50_000))
    t = np.concatenate([p.t for p in parts])
    u = np.concatenate([p.u for p in parts])
    bright = t > 200
    assert bright.sum() > 10_000
    assert np.mean(u[bright]) == pytest.approx(np.mean(t[bright]) / truth.gain + model[1], rel=0.05)
