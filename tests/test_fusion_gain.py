"""Temporal fusion of the library's stream against the single-frame default (issue 26.2-3): the noise model a
stream estimates is read from pixels the motion tests found still, still regions gain, moving ones do not lose."""

from __future__ import annotations

import numpy as np
import pytest

import svelive
from svelive.core.pattern import Pattern
from svelive.core.sensor import Sensor
from svelive.noise import variance_uncertainty
from svelive.scenes import moving_disc, render_sequence
from svelive.simulation import exposure_scale, load_sample_scene

PATTERN = "1,4/16,64"
LEVELS = dict(black_level=64, white_level=4095)


def crossing_disc(name: str, sensor: Sensor, stops: float, n: int, seed: int = 1) -> list:
    """``n`` frames of a shipped crop ``stops`` under full scale with a disc at twice its 99.9th percentile
    crossing it at 20 px a frame (the longer exposures clip on it: its edges reset the history by their
    readings' censoring, not by the noise test)."""
    scene = np.maximum(load_sample_scene(name), 0)
    scene = scene * exposure_scale(scene, Pattern.parse(PATTERN), sensor, stops_below_fill=stops)
    h, w = scene.shape
    disc = moving_disc(scene, 2.0 * float(np.percentile(scene, 99.9)), radius=min(h, w) / 10,
                       start=(h / 2, 0.1 * w), velocity=(0.0, 20.0))
    return list(render_sequence(disc, n, PATTERN, sensor, seed=seed))


@pytest.mark.parametrize("full_well, read_e", [(10_000, 12.0), (40_000, 6.0)])
def test_a_bright_object_crossing_does_not_spoil_the_streams_noise_model(full_well, read_e):
    """The tracker is fed the pixels that kept their history (SequenceResult.still), not those outside the
    motion mask: the disc's edges, reset where readings crossed the censor level, are no motion, and their
    differences read the gain 2-4x too high (the model then untrusted: every later frame its single frame)."""
    sensor = Sensor.from_full_well(12, full_well, read_e, **LEVELS)
    frames = crossing_disc("mttamwest", sensor, 5.0, 4)
    stream = svelive.Reconstructor(PATTERN, **LEVELS)
    for f in frames:
        result = stream.process(f.raw)
    noise = stream.noise
    # the schedule's trust bound and the estimate's own stated uncertainty, not a number fitted to this scene
    assert stream.noise_trusted and variance_uncertainty(noise) <= stream.noise_schedule.trusted_below
    assert abs(noise.gain / sensor.gain - 1) < 3 * noise.gain_sigma / noise.gain + 0.05, noise.describe()
    changed = np.abs(frames[-1].truth - frames[-2].truth) > 0.05 * np.maximum(frames[-1].truth, 1.0)
    assert np.mean(result.still[changed]) < 0.01  # what changed is not offered to the tracker as still


class _FittedTracker:
    """A NoiseTracker stand-in whose fits are given in order (StreamNoise calls add, rest and fit)."""

    def __init__(self, fits):
        self.fits = list(fits)

    def add(self, raw, camera, static, *, signal=None):
        pass

    def rest(self):
        pass

    def fit(self):
        return self.fits.pop(0)


def test_the_first_runs_last_fit_supersedes_its_pair_fit_and_later_runs_still_conflict():
    """The fit after frame 2 reads a pair, the fit after frame 3 the same samples and the three frames' (unbiased)
    ones: a disagreement between them is the pair's error, not contamination (a confidently wrong pair left the
    stream unfused until its next run, 64 frames on). A later run that disagrees still marks the model untrusted."""
    from svelive.noise import NoiseEstimate, NoiseSchedule, StreamNoise

    pair = NoiseEstimate(2.0, 1.0, 0.1, 0.02, 0, "estimated")
    triple = NoiseEstimate(1.0, 1.0, 0.03, 0.02, 0, "estimated")
    stray = NoiseEstimate(3.0, 1.0, 0.05, 0.02, 0, "estimated")
    noise = StreamNoise(NoiseSchedule(run_frames=3, refit_every=4), tracker=_FittedTracker([pair, triple, stray]))
    frame, camera = np.zeros((4, 4), np.uint16), None
    still = np.ones((4, 4), bool)
    noise.observe(frame, camera, None)
    assert noise.observe(frame, camera, still) is pair and noise.trusted
    assert noise.observe(frame, camera, still) is triple and noise.trusted
    for static in (None, None, still, still):  # frame 4 waits, 5-7 are the second run
        noise.observe(frame, camera, static)
    assert noise.estimate is triple and not noise.trusted


def _object_case(sensor: Sensor, stops: float, frames: int = 8):
    """A dim shipped crop (desk, 128 px) crossed at 22 px a frame by a disc of textured mttamwest 3 stops brighter
    than the scene's 99.9th percentile; PU21 and ghost residue of the README stream, the stream given the true
    model and the single-frame default (svelive.bench.motion_cases.run_case)."""
    from svelive.bench import motion_cases as mc
    from svelive.metrics import PU21_PEAK, display_scale, pu21_encode

    def pu21(image, truth, region):
        s = display_scale(truth)
        err = pu21_encode(image[region] * s) - pu21_encode(truth[region] * s)
        return float(10 * np.log10(PU21_PEAK ** 2 / max(float(np.mean(err * err)), 1e-12)))

    background = mc.dim(np.maximum(load_sample_scene("desk"), 0)[64:192, 64:192], PATTERN, sensor, stops)
    texture = np.maximum(load_sample_scene("mttamwest"), 0)[:96, :96]
    texture = texture * (8 * float(np.percentile(background, 99.9)) / float(np.percentile(texture, 99.9)))
    scene = mc.moving_texture(background, texture, 16, (64, 20), (0.0, 22.0))
    streams = {"readme": lambda raws: svelive.Reconstructor(PATTERN, **LEVELS),
               "true": lambda raws: svelive.Reconstructor(PATTERN, **LEVELS, gain=sensor.gain,
                                                          read_noise=sensor.read_noise)}
    single = {"readme": lambda raw: svelive.reconstruct(raw, PATTERN, **LEVELS),
              "true": lambda raw: svelive.reconstruct(raw, PATTERN, **LEVELS, gain=sensor.gain,
                                                      read_noise=sensor.read_noise)}
    return {name: mc.run_case(scene, frames, PATTERN, sensor, {name: streams[name]}, single[name], pu21, seed=5)
            for name in streams}


@pytest.fixture(scope="module")
def object_case():
    return _object_case(Sensor.from_full_well(12, 3_000, 2.0, **LEVELS), 5.0)


def test_a_textured_object_crossing_a_dark_scene_leaves_no_trail_and_moving_pixels_keep_their_frame(object_case):
    """Moving pixels within 0.3 dB of the single frame with the same model (issue 26.3's target; the method's own
    response to a different model is not the fusion's), and no more of a change shown by the stream's trail
    pixels than by the single frame's: a history leaking into a pixel fused over n <= max_history = 8 frames
    shows at least 1/8 of the change there, so a mean excess of 1/32 is a quarter of the trail leaking."""
    scores = object_case["true"]
    moving = np.array(scores.pu21[("true", "moving")][1:]) - np.array(scores.pu21[("single", "moving")][1:])
    assert np.nanmin(moving) > -0.3, np.round(moving, 2)
    for name, case in object_case.items():
        excess = np.nanmean(case.ghost[name][1:]) - np.nanmean(case.ghost["single"][1:])
        assert excess < 1 / 32, (name, excess)


def test_still_regions_of_the_readme_stream_gain_3_db_at_frame_8_beside_a_moving_object(object_case):
    scores = object_case["readme"]
    gain = scores.pu21[("readme", "still")][7] - scores.pu21[("single", "still")][7]
    assert gain >= 3.0, gain  # issue 26.2's target, over the single-frame default


def test_an_untrusted_model_is_refitted_sooner_with_gaps_doubling_then_on_the_schedule_once_trusted():
    """While the model is not trusted the stream shows single frames; the next runs then start 0, 3, 9 frames after
    the last (not refit_every - run_frames = 61), and once a fit is trusted the schedule's gap returns."""
    from svelive.noise import NoiseEstimate, NoiseSchedule, StreamNoise

    vague = NoiseEstimate(1.0, 1.0, 0.5, 0.5, 0, "estimated")  # 50 %: not trusted
    sharp = NoiseEstimate(1.0, 1.0, 0.01, 0.01, 0, "estimated")
    noise = StreamNoise(NoiseSchedule(run_frames=3, refit_every=64), tracker=_FittedTracker([vague] * 4 + [sharp]))
    frame, still = np.zeros((4, 4), np.uint16), np.ones((4, 4), bool)
    fitted_at = []
    for k in range(1, 80):
        fits = noise.fits
        noise.observe(frame, None, still if noise.needs_static() else None)
        if noise.fits > fits:
            fitted_at.append(k)
    # runs 1-3 (fits after 2, 3), 4-6, 10-12, 22-24 (trusted), then none before frame 22 + 64
    assert fitted_at == [2, 3, 6, 12, 24], fitted_at
    assert noise.trusted


def _fitted_at(noise, frames: int, settle=lambda: None) -> list[int]:
    """The frames (1-based) after which ``noise`` took a fit, feeding it ``frames`` still frames; ``settle`` waits
    for its executor's work before the next frame."""
    frame, still = np.zeros((4, 4), np.uint16), np.ones((4, 4), bool)
    fitted_at = []
    for k in range(1, frames + 1):
        fits = noise.fits
        noise.observe(frame, None, still if noise.needs_static() else None)
        settle()
        if noise.fits > fits:
            fitted_at.append(k)
    return fitted_at


def test_a_trusted_model_whose_fits_agree_is_refitted_ever_later_and_on_the_schedule_again_after_a_disagreement():
    """Each later run's fit that agrees with the trusted model doubles the gap between runs (run start to run start:
    8, 16, 32, then refit_max = 32); a fit that disagrees distrusts the model (the next run at once), and the fit
    that agrees again brings the schedule's gap back, not the backed-off one."""
    from svelive.noise import NoiseEstimate, NoiseSchedule, StreamNoise

    sharp = NoiseEstimate(1.0, 1.0, 0.01, 0.01, 0, "estimated")
    stray = NoiseEstimate(3.0, 1.0, 0.01, 0.01, 0, "estimated")
    fits = [sharp] * 5 + [stray] + [sharp] * 4
    noise = StreamNoise(NoiseSchedule(run_frames=3, refit_every=8, refit_max=32), tracker=_FittedTracker(fits))
    # runs 1-3 (fits after 2, 3), 9-11, 25-27, 57-59, 89-91 (stray), 92-94, 100-102
    assert _fitted_at(noise, 105) == [2, 3, 11, 27, 59, 91, 94, 102]
    assert noise.trusted and noise.estimate is sharp
    from svelive.core.errors import SveliveError

    with pytest.raises(SveliveError, match="refit_max"):  # a bound below the schedule's own gap
        NoiseSchedule(refit_every=64, refit_max=32)


def test_on_a_noise_thread_a_disagreeing_fit_cuts_a_backed_off_gap_to_the_schedules():
    """With an executor the gap after a run is chosen before that run's fit is done (from the fits before it); a
    fit that then disagrees leaves at most the schedule's gap from the run's end, not the backed-off one."""
    from concurrent.futures import ThreadPoolExecutor

    from svelive.noise import NoiseEstimate, NoiseSchedule, StreamNoise

    sharp = NoiseEstimate(1.0, 1.0, 0.01, 0.01, 0, "estimated")
    stray = NoiseEstimate(3.0, 1.0, 0.01, 0.01, 0, "estimated")
    fits = [sharp] * 5 + [stray] + [sharp] * 4
    with ThreadPoolExecutor(1) as pool:
        noise = StreamNoise(NoiseSchedule(run_frames=3, refit_every=8, refit_max=32), tracker=_FittedTracker(fits),
                            executor=pool)
        fitted_at = _fitted_at(noise, 90, settle=lambda: pool.submit(lambda: None).result())
    # gaps chosen one fit late: runs 1-3, 9-11, 17-19, 33-35, 65-67 (stray, its gap of 29 cut to 5), 73-75, 76-78
    assert fitted_at == [2, 3, 11, 19, 35, 67, 75, 78, 86]
    assert noise.error is None and noise.trusted
