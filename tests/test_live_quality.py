"""The live-quality ladder (service.pipeline.quality): its decisions on made-up streams, and a real pipeline
whose top step is slowed on purpose holding the camera's rate by stepping down."""

from __future__ import annotations

import dataclasses
import time

import pytest

from service.pipeline import Pipeline, PipelineConfig
from service.pipeline.quality import LiveQuality, QualityConfig
from svelive.core.errors import SveliveError
from svelive.reconstruction.live import LADDER, ladder_for
from svelive.reconstruction.methods import METHODS

FRAME_NS = 33_000_000  # a 30 fps camera


def names(steps) -> list[str]:
    return [step.name for step in steps]


def test_ladder_starts_at_the_configured_setting_and_only_gets_cheaper():
    assert names(ladder_for("adaptive", True)) == ["adaptive+fusion", "weighted+fusion", "adaptive", "weighted"]
    assert names(ladder_for("weighted", True)) == ["weighted+fusion", "adaptive", "weighted"]
    assert names(ladder_for("adaptive", False)) == ["adaptive", "weighted"]  # no fusion added
    assert names(ladder_for("cubic", True)) == ["cubic+fusion"]  # outside the ladder: no step known cheaper
    assert names(ladder_for("aggregate", False)) == ["aggregate"]
    assert names(ladder_for("adaptive", True, "fixed")) == ["adaptive+fusion"]
    costs = [step.cost for step in LADDER]
    assert costs == sorted(costs, reverse=True) and len(set(costs)) == len(costs)
    with pytest.raises(SveliveError, match="live quality must be one of adaptive, fixed"):
        ladder_for("adaptive", True, "sometimes")


def feed(quality: LiveQuality, seconds: float, ms_of, lost_every: dict[str, int], start_ns: int = 0,
         counts: list[int] | None = None, rows_of=lambda name: 1.0) -> int:
    """A 30 fps camera for ``seconds``: each arrival publishes a frame of the current step taking
    ``ms_of(step name)`` ms, its method on ``rows_of(step name)`` of the rows, except one in
    ``lost_every[step name]`` (dropped: the reconstruction was busy).
    Returns the time reached; ``counts`` ([arrived, lost]) carries on between calls."""
    counts = counts if counts is not None else [0, 0]
    now = start_ns
    for _ in range(int(seconds * 1e9 / FRAME_NS)):
        now += FRAME_NS
        counts[0] += 1
        step = quality.step
        every = lost_every.get(step.name, 0)
        if every and counts[0] % every:
            counts[1] += 1
            continue
        quality.observe(now, counts[0], counts[1], ms_of(step.name), step, rows_of(step.name))
    return now


def stepped_down(quality: LiveQuality, counts: list[int] | None = None, ms: float = 60.0) -> int:
    """3 s of the top step taking ``ms`` a frame with two frames in three lost: the ladder steps down to
    weighted+fusion (asserted); returns the time reached (``counts`` as :func:`feed`'s)."""
    now = feed(quality, 3.0, lambda name: ms, {"adaptive+fusion": 3}, counts=counts)
    assert quality.step.name == "weighted+fusion"
    return now


def test_steps_down_while_behind_and_says_why():
    quality = LiveQuality("adaptive", True)
    slow = {"adaptive+fusion": 3, "weighted+fusion": 3}  # two frames in three lost at the fused steps
    feed(quality, 6.0, lambda name: 60.0 if name.endswith("fusion") else 20.0, slow)
    state = quality.state()
    assert state["step"] == 2 and state["name"] == "adaptive" and state["changes"] == 2
    assert "frames dropped" in state["reason"] and "weighted+fusion takes 60 ms" in state["reason"]


def test_a_burst_of_losses_with_a_fast_reconstruction_is_not_falling_behind():
    quality = LiveQuality("adaptive", True)
    counts = [0, 0]
    now = feed(quality, 3.0, lambda name: 12.0, {}, counts=counts)
    counts[1] += 10  # a noise estimate held the thread: ten frames lost at once
    feed(quality, 3.0, lambda name: 12.0, {}, start_ns=now, counts=counts)
    assert quality.state()["step"] == 0 and quality.state()["changes"] == 0


def test_steps_back_up_with_headroom_after_the_hold_and_holds_longer_when_that_fails():
    config = QualityConfig(hold_s=5.0)
    quality = LiveQuality("adaptive", True, config=config)
    counts = [0, 0]
    busy = {"adaptive+fusion": 3}
    now = feed(quality, 3.0, lambda name: 60.0, busy, counts=counts)
    assert quality.step.name == "weighted+fusion"
    now = feed(quality, 4.0, lambda name: 15.0, busy, start_ns=now, counts=counts)
    assert quality.step.name == "weighted+fusion", "stepped up before the hold"
    now = feed(quality, 2.0, lambda name: 15.0, busy, start_ns=now, counts=counts)
    assert quality.step.name == "adaptive+fusion" and "headroom" in quality.state()["reason"]
    # the step up does not hold: back down, and the next try waits twice as long
    now = feed(quality, 2.5, lambda name: 60.0, busy, start_ns=now, counts=counts)
    assert quality.step.name == "weighted+fusion" and quality.state()["hold_s"] == 10.0
    now = feed(quality, 7.0, lambda name: 15.0, busy, start_ns=now, counts=counts)
    assert quality.step.name == "weighted+fusion"
    feed(quality, 4.0, lambda name: 15.0, busy, start_ns=now, counts=counts)
    assert quality.step.name == "adaptive+fusion"


def test_no_step_up_without_headroom():
    quality = LiveQuality("adaptive", True, config=QualityConfig(hold_s=2.0))
    counts = [0, 0]
    now = stepped_down(quality, counts)
    # 28 ms of 33: the step above (cost 1 / 0.83 of it) would not fit in 80 % of the interval
    feed(quality, 10.0, lambda name: 28.0, {}, start_ns=now, counts=counts)
    assert quality.step.name == "weighted+fusion"


@pytest.mark.parametrize("rows, below", [(1.0, "weighted+fusion"), (0.5, "adaptive"), (0.125, "weighted")])
def test_a_top_step_the_band_refresh_made_cheaper_steps_down_to_a_cheaper_step(rows, below):
    """A still view whose top step ran the method on ``rows`` of the frame (the band refresh) costs
    1 - 0.34 (1 - rows) of its declared cost (0.83 at 1/2, 0.70 at 1/8): falling behind, it steps down
    to the first step below 0.9 of that (weighted+fusion 0.83, adaptive 0.68, weighted 0.47)."""
    quality = LiveQuality("adaptive", True)
    feed(quality, 3.0, lambda name: 60.0, {"adaptive+fusion": 3}, rows_of=lambda name: rows)
    assert quality.step.name == below and quality.state()["changes"] == 1


def test_a_step_up_goes_to_the_best_step_predicted_to_fit_by_its_cost_as_it_ran():
    """Back up from below a refreshed top step: the top's cost as it last ran (0.70, the method on 1/8 of
    the rows) predicts it fits, so the ladder goes straight to it, past adaptive and weighted+fusion
    (declared 0.68 and 0.83), which would fit too."""
    quality = LiveQuality("adaptive", True, config=QualityConfig(hold_s=2.0))
    counts = [0, 0]
    rows = {"adaptive+fusion": 0.125}
    now = feed(quality, 3.0, lambda name: 60.0, {"adaptive+fusion": 3}, counts=counts,
               rows_of=lambda name: rows.get(name, 1.0))
    assert quality.step.name == "weighted"
    # 12 ms of 33: the top predicted at 12 x 0.70 / 0.47 = 17.9 ms fits in 80 % of the interval
    feed(quality, 5.0, lambda name: 12.0, {}, start_ns=now, counts=counts, rows_of=lambda name: rows.get(name, 1.0))
    assert quality.step.name == "adaptive+fusion" and quality.state()["changes"] == 2


def test_fixed_mode_keeps_the_setting_and_reports_that_it_is_behind():
    quality = LiveQuality("adaptive", True, mode="fixed")
    feed(quality, 5.0, lambda name: 80.0, {"adaptive+fusion": 3})
    state = quality.state()
    assert state["step"] == 0 and state["behind"] and "(fixed: no step down)" in state["reason"]


def test_frames_of_an_earlier_step_are_not_evidence():
    quality = LiveQuality("adaptive", True)
    old = quality.steps[0]
    stepped_down(quality)
    for i in range(200):  # late frames of the step above, all slow and lossy: ignored
        quality.observe(10**10 + i * FRAME_NS, 10_000 + i, 5_000 + i, 90.0, old)
    assert quality.step.name == "weighted+fusion"


def test_a_new_method_starts_its_own_ladder_at_the_top():
    quality = LiveQuality("adaptive", True)
    stepped_down(quality)
    quality.configure("weighted", True)
    assert quality.state()["step"] == 0 and names(quality.steps) == ["weighted+fusion", "adaptive", "weighted"]


# ----- a real pipeline, slowed on purpose -----------------------------------------------------------------------

SLOW_S = 0.3  # the slowed step's time per frame: 3 fps at most, against a 10 fps camera


@pytest.fixture
def slow_method(monkeypatch):
    """The ladder's top method, ``adaptive``, slowed by a 0.3 s sleep per frame (an artificially slowed
    reconstruction; the steps below it with ``weighted`` are not)."""
    spec = METHODS["adaptive"]

    def run(inp, **options):
        time.sleep(SLOW_S)
        return spec.run(inp, **options)

    monkeypatch.setitem(METHODS, "adaptive", dataclasses.replace(spec, run=run))
    return "adaptive"


def delivered_share(pipeline: Pipeline, seconds: float) -> tuple[float, dict]:
    """Frames reconstructed over frames captured during ``seconds``, and the state at the end."""
    before = pipeline.state()
    time.sleep(seconds)
    after = pipeline.state()
    captured = after["frames"]["captured"] - before["frames"]["captured"]
    reconstructed = after["frames"]["reconstructed"] - before["frames"]["reconstructed"]
    assert captured > 0.5 * 10 * seconds, f"the camera delivered only {captured} frames"
    return reconstructed / captured, after


def wait_for_frames(pipeline: Pipeline, n: int, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while pipeline.state()["frames"]["reconstructed"] < n:
        assert time.monotonic() < deadline, "no reconstructed frames"
        time.sleep(0.1)


@pytest.mark.parametrize("mode", ["adaptive", "fixed"])
def test_a_slowed_reconstruction_steps_down_and_holds_the_cameras_rate(slow_method, mode):
    config = PipelineConfig(source="demo", source_options={"width": 320, "height": 200, "fps": 10},
                            method=slow_method, live_quality=mode, workers=1)
    with Pipeline(config) as pipeline:
        wait_for_frames(pipeline, 2)
        time.sleep(3.0)  # the evidence window, then a step down
        share, state = delivered_share(pipeline, 4.0)
    quality = state["live_quality"]
    if mode == "fixed":
        assert quality["step"] == 0 and quality["behind"] and "fixed" in quality["reason"]
        assert share < 0.5, f"the slowed step kept {share:.0%} of the frames"
        assert state["drops"]["reconstruct_busy"] > 0
    else:
        assert quality["step"] >= 1 and quality["method"] == "weighted", quality
        assert "frames dropped" in quality["reason"] and "adaptive+fusion takes" in quality["reason"]
        assert share >= 0.9, f"after stepping down only {share:.0%} of the camera's frames were reconstructed"
        assert state["method"] == "adaptive"  # the configured method is still what the user chose


def test_a_gap_in_the_frames_is_not_evidence_of_headroom():
    """A source that went offline: the first frames after the gap do not make a window, so no step up on them."""
    quality = LiveQuality("adaptive", True, config=QualityConfig(hold_s=2.0))
    counts = [0, 0]
    now = stepped_down(quality, counts)
    now = feed(quality, 2.5, lambda name: 30.0, {}, start_ns=now, counts=counts)  # no headroom: 30 of 33 ms
    assert quality.step.name == "weighted+fusion"
    now += 60 * 10**9  # a minute offline
    for i in range(3):  # two fast frames after it
        counts[0] += 1
        quality.observe(now + i * FRAME_NS, counts[0], counts[1], 5.0, quality.step)
    assert quality.step.name == "weighted+fusion"


def test_frames_reconstructed_in_parallel_are_judged_per_frame_interval():
    """With two frames at once each may take two frame intervals: 50 ms of 33 with no drops is headroom enough
    to try the step above (25 ms a frame), not a reason to stay."""
    quality = LiveQuality("adaptive", True, config=QualityConfig(hold_s=2.0), parallel=2)
    counts = [0, 0]
    now = stepped_down(quality, counts, ms=150.0)
    feed(quality, 4.0, lambda name: 40.0, {}, start_ns=now, counts=counts)
    assert quality.step.name == "adaptive+fusion"


def test_frames_slower_than_the_window_are_still_judged():
    """A step that takes 3 s a frame against a 30 fps camera (97 % of the frames lost) steps down, and in fixed
    mode says it is behind, although no two of its frames fall within one 2 s window."""
    for mode in ("adaptive", "fixed"):
        quality = LiveQuality("adaptive", True, mode=mode)
        feed(quality, 8.0, lambda name: 3000.0 if name == "adaptive+fusion" else 20.0, {"adaptive+fusion": 90})
        state = quality.state()
        if mode == "adaptive":
            assert state["step"] >= 1, state
        else:
            assert state["behind"] and state["step"] == 0, state


def test_the_same_setting_again_keeps_the_step():
    """A client that PUTs every setting, the method unchanged, does not reset the ladder."""
    quality = LiveQuality("adaptive", True)
    stepped_down(quality)
    quality.configure("adaptive", True)
    assert quality.step.name == "weighted+fusion" and quality.state()["changes"] == 1
