"""The live noise model: a camera not told its gain and read noise gets them from its own frames."""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from service.pipeline import Pipeline, PipelineConfig
from svelive import Sensor
from svelive.core.pattern import Pattern
from svelive.simulate import exposure_scale, load_sample_scene, simulate
from tests.test_service_helpers import PATTERN, Camera, SimSource

TRUE = Sensor.from_full_well(12, 6_000, 6)  # gain 1.47 e-/DN, read noise 4.1 DN: far from the defaults


class UntoldSource(SimSource):
    """The simulated camera, its sensor's levels known but not its gain and read noise."""

    def __init__(self, camera: Camera) -> None:
        super().__init__(camera)
        self.camera = self.camera.replace(sensor=dataclasses.replace(self.camera.sensor, gain=None, read_noise=None))


def static_camera(n: int = 8) -> Camera:
    """A still view: the same scene in every frame, new noise each time (the true sensor)."""
    pattern = Pattern.parse(PATTERN)
    scene = load_sample_scene("desk")[:192, :224]
    scene = np.maximum(scene, 0) * exposure_scale(scene, pattern, TRUE, stops_below_fill=2)
    rng = np.random.default_rng(3)
    return Camera(fps=20, raws=[simulate(np.ascontiguousarray(scene), pattern, TRUE, seed=rng).raw for _ in range(n)])


def test_the_live_service_estimates_and_uses_the_noise_model():
    config = PipelineConfig(source="sim", temporal=True, offline_after_s=0.6, retry_s=0.2)
    pipeline = Pipeline(config, lambda: UntoldSource(static_camera()))
    pipeline.reconstruction.noise.interval_s = 0.3
    with pipeline:
        deadline = time.monotonic() + 60
        while (pipeline.reconstruction.noise.updates < 4 or pipeline.latest() is None
               or pipeline.latest().hdr.camera.sensor.gain is None):
            assert time.monotonic() < deadline, f"no estimate in use: {pipeline.reconstruction.noise.state()}"
            time.sleep(0.1)
        state = pipeline.reconstruction.noise.state()
        published = pipeline.latest()
        used = published.hdr.camera.sensor
        described = pipeline.reconstruction.noise.model_of(published.hdr.camera).attributes()
    assert described["noiseSource"] == state["in_use"]["source"] and described["noiseGain"] == used.gain
    assert state["source"] != "given" and state["runs"] >= 4 and state["in_use"] is not None
    # the read noise is what the weights need most; the defaults (3 e- at 10 000 e- full well) say 1.2 DN
    assert abs(used.read_noise - TRUE.read_noise) < 0.15 * TRUE.read_noise, (used, TRUE)
    assert abs(used.gain - TRUE.gain) < 0.3 * TRUE.gain, (used, TRUE)


def test_a_given_noise_model_is_never_replaced():
    config = PipelineConfig(source="sim", temporal=True, offline_after_s=0.6, retry_s=0.2)
    pipeline = Pipeline(config, lambda: SimSource(static_camera(4)))
    pipeline.reconstruction.noise.interval_s = 0.1
    with pipeline:
        deadline = time.monotonic() + 30
        while pipeline.reconstructed.count < 10:
            assert time.monotonic() < deadline
            time.sleep(0.05)
        assert pipeline.reconstruction.noise.state() is None
        assert pipeline.latest().hdr.camera.sensor == SimSource(static_camera(1)).camera.sensor


def test_frames_dropped_between_reconstructed_ones_still_make_runs():
    """Live at full size the reconstruction takes the newest frame and the ids between are dropped; three
    frames reconstructed one after another (static by their motion masks against the fused history) still
    make a run for the tracker, and a frame id that goes back (a replay loop) starts afresh."""
    import threading

    from service.pipeline.noise import NoiseStage
    from svelive.core.frame import Frame

    camera = static_camera(1)
    untold = UntoldSource(camera).camera
    stage = NoiseStage(threading.Event(), interval_s=0.0)
    still = np.zeros((8, 8), bool)
    raw = np.zeros((8, 8), np.uint16)
    for frame_id in (0, 4, 9):
        stage.offer(Frame(raw, frame_id=frame_id, host_time_ns=0, camera=untold), untold, still)
    taken, run = stage._runs.get_newest(0, 0)
    assert [f.frame_id for f in run.frames] == [0, 4, 9] and len(run.static) == 2
    for frame_id in (12, 3, 5):
        stage.offer(Frame(raw, frame_id=frame_id, host_time_ns=0, camera=untold), untold, still)
    assert stage._runs.get_newest(taken, 0) is None


def test_unfused_frames_are_not_offered_as_still():
    """Without fusion a frame's motion mask is all False and says nothing of which pixels are still: the noise
    stage gets no run of such frames (it took them as still and fitted moving pixels' differences)."""
    import time

    from service.pipeline import Pipeline, PipelineConfig

    config = PipelineConfig(source="demo", source_options={"width": 160, "height": 96, "fps": 15}, temporal=False,
                            live_quality="fixed")
    with Pipeline(config) as pipeline:
        deadline = time.monotonic() + 30
        while pipeline.state()["frames"]["reconstructed"] < 20:
            assert time.monotonic() < deadline, "no frames"
            time.sleep(0.1)
        time.sleep(1.0)  # a run offered at the 3rd frame would have been fitted by now
        assert pipeline.reconstruction.noise.updates == 0
