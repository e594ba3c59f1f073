"""The real-time path: frames spread over threads give exactly the single-thread results."""

from __future__ import annotations

import numpy as np
import pytest

from svelive import Pattern, Sensor, SveliveError
from svelive.reconstruction.config import MotionConfig
from svelive.reconstruction.fusion import fuse
from svelive.reconstruction.stream import Reconstructor
from svelive.scenes import moving_disc, panning, render_sequence
from svelive.simulate import exposure_scale, load_sample_scene

import svelive.reconstruction.stream as reconstructor_module

PATTERN = "1,4/16,64"
SENSOR = Sensor.from_full_well(12, 10_000, 3)
KW = dict(white_level=SENSOR.white_level, gain=SENSOR.gain, read_noise=SENSOR.read_noise)


def scene(stops: float) -> np.ndarray:
    image = np.maximum(load_sample_scene("cannon"), 0)
    return image * np.float32(exposure_scale(image, Pattern.parse(PATTERN), SENSOR, stops_below_fill=stops))


def run(frames, monkeypatch, strip_rows: int, **kw) -> list:
    monkeypatch.setattr(reconstructor_module, "fuse",
                        lambda *args, **kwargs: fuse(*args, **kwargs, strip_rows=strip_rows))
    r = Reconstructor(PATTERN, **KW, **kw)
    return [r.process(f.raw) for f in frames]


@pytest.mark.parametrize("case", ["disc", "pan", "integration"])
def test_strips_and_threads_change_nothing(case, monkeypatch):
    # a saturating disc (lower bounds, censor crossings), a pan (global reset), the consistency test
    image = scene(0)
    if case == "pan":
        frames = render_sequence(panning(image, (120, 160), (2.0, 3.0)), 4, PATTERN, SENSOR, seed=2)
    else:
        disc = moving_disc(image[:120, :160], float(image.max() * 4), 14.0, (50.0, 40.0), (3.0, 5.0))
        frames = render_sequence(disc, 5, PATTERN, SENSOR, seed=2,
                                 timing="integration" if case == "integration" else "mask")
    frames = list(frames)
    kw = dict(exposure_timing="integration") if case == "integration" else {}
    whole = run(frames, monkeypatch, 10**6, workers=1, **kw)  # one strip: the whole frame at once
    for strip_rows, workers in ((16, 2), (7, 3), (64, 1)):
        parts = run(frames, monkeypatch, strip_rows, workers=workers, **kw)
        for a, b in zip(whole, parts):
            for name in ("image", "variance", "motion", "weight", "lower_bound"):
                np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=f"{name} {strip_rows}")
            assert a.moving_fraction == b.moving_fraction
    fractions = [r.moving_fraction for r in whole[1:]]
    if case == "pan":
        assert min(fractions) == 1.0  # the global reset path was taken
    else:
        assert 0 < min(fractions) and max(fractions) < 0.5
        assert any(r.lower_bound.any() for r in whole)  # the saturated-disc paths were taken


def test_workers_option_is_checked():
    assert Reconstructor(PATTERN, **KW, workers=2).workers == 2
    for bad in (0, -1, 1.5, True, 100):
        with pytest.raises(SveliveError, match="workers"):
            Reconstructor(PATTERN, **KW, workers=bad)
    assert MotionConfig().widen == 1  # the halo the strips read is derived from it
