"""Temporal fusion of the library's stream against the single-frame default (issue 26.2-3): the noise model a
stream estimates is read from pixels the motion tests found still, still regions gain, moving ones do not lose."""

from __future__ import annotations

import numpy as np
import pytest

import svelive
from svelive.noise import variance_uncertainty
from svelive.pattern import Pattern
from svelive.scenes import moving_disc, render_sequence
from svelive.sensor import Sensor
from svelive.simulate import exposure_scale, load_sample_scene

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
