"""The live noise model: a camera not told its gain and read noise gets them from its own frames."""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from service.pipeline import Pipeline, PipelineConfig
from svelive import Sensor
from svelive.core.pattern import Pattern
from svelive.simulation import exposure_scale, load_sample_scene, simulate
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


def test_the_live_service_estimates_and_uses_the_noise_model(monkeypatch):
    """The service runs the library stream's model (one code path): the first frame's estimate, then fits of
    runs of frames on the stream's noise thread (never on a reconstruction thread), fusion once trusted."""
    import threading

    from svelive.noise import NoiseTracker

    threads = []
    fit = NoiseTracker.fit
    monkeypatch.setattr(NoiseTracker, "fit", lambda self: threads.append(threading.current_thread().name) or fit(self))
    config = PipelineConfig(source="sim", temporal=True, offline_after_s=0.6, retry_s=0.2)
    pipeline = Pipeline(config, lambda: UntoldSource(static_camera()))
    with pipeline:
        deadline = time.monotonic() + 60
        while True:
            state, published = pipeline.reconstruction.noise_state(), pipeline.latest()
            if state is not None and state["trusted"] and published is not None and published.noise is not None \
                    and published.noise.gain == state["gain"]:
                break
            assert time.monotonic() < deadline, f"no trusted estimate in use: {state}"
            time.sleep(0.1)
        used = published.hdr.camera.sensor
        described = published.noise.attributes()
        # the model is refined as frames come: a second fit follows (the first run fits after its second and
        # its last frame; a first fit may already be trusted, so the second can come after the trust)
        while state["fits"] < 2:
            assert time.monotonic() < deadline, f"no second fit: {state}"
            time.sleep(0.1)
            state = pipeline.reconstruction.noise_state()
    assert threads and all(name.startswith("svelive-noise") for name in threads), threads
    assert state["source"] == "estimated" and state["fits"] >= 2 and state["error"] is None
    assert described["noiseSource"] == "estimated" and described["noiseGain"] == used.gain
    # the read noise is what the weights need most; the defaults (3 e- at 10 000 e- full well) say 1.2 DN
    assert abs(used.read_noise - TRUE.read_noise) < 0.15 * TRUE.read_noise, (used, TRUE)
    assert abs(used.gain - TRUE.gain) < 0.3 * TRUE.gain, (used, TRUE)


def test_a_given_noise_model_is_never_replaced():
    config = PipelineConfig(source="sim", temporal=True, offline_after_s=0.6, retry_s=0.2)
    pipeline = Pipeline(config, lambda: SimSource(static_camera(4)))
    with pipeline:
        deadline = time.monotonic() + 30
        while pipeline.reconstructed.count < 10:
            assert time.monotonic() < deadline
            time.sleep(0.05)
        assert pipeline.reconstruction.noise_state() is None
        published = pipeline.latest()
        assert published.hdr.camera.sensor == SimSource(static_camera(1)).camera.sensor
        assert published.noise.source == "given"


def test_a_model_fitted_on_a_thread_is_the_one_fitted_in_line():
    """StreamNoise with an executor (the service's) takes the same models as without (the library's), one
    run of three frames: the fits after its second and third frames."""
    from concurrent.futures import ThreadPoolExecutor

    from svelive.noise import StreamNoise

    camera = UntoldSource(static_camera(1)).camera
    raws = static_camera(3).raws
    still = np.ones(raws[0].shape, bool)
    inline = StreamNoise()
    with ThreadPoolExecutor(1) as pool:
        threaded = StreamNoise(executor=pool)
        for i, raw in enumerate(raws):
            for noise in (inline, threaded):
                noise.first(raw, camera)
                noise.observe(raw, camera, None if i == 0 else still)
    assert inline.fits == threaded.fits == 2 and threaded.error is None
    assert threaded.estimate == inline.estimate and threaded.trusted == inline.trusted
    assert inline.estimate.source == "estimated"


def test_unfused_frames_are_not_offered_as_still():
    """Without fusion a frame's motion mask is all False and says nothing of which pixels are still: the
    stream's noise model gets no run of such frames (it took them as still and fitted moving pixels'
    differences)."""
    config = PipelineConfig(source="demo", source_options={"width": 160, "height": 96, "fps": 15}, temporal=False,
                            live_quality="fixed")
    with Pipeline(config) as pipeline:
        deadline = time.monotonic() + 30
        while pipeline.state()["frames"]["reconstructed"] < 20:
            assert time.monotonic() < deadline, "no frames"
            time.sleep(0.1)
        time.sleep(1.0)  # a run offered at the 3rd frame would have been fitted by now
        state = pipeline.reconstruction.noise_state()
        assert state is not None and state["fits"] == 0 and not state["trusted"]
