"""The real-time path: frames spread over threads give exactly the single-thread results; the encoder stage
counts every frame once (encoded, not watched, or dropped while busy)."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

import svelive.reconstruction.stream as reconstructor_module
from svelive import Pattern, Sensor, SveliveError
from svelive.reconstruction.fusion import fuse
from svelive.reconstruction.stream import Reconstructor, default_method
from svelive.scenes import moving_disc, panning, render_sequence
from svelive.simulation import exposure_scale, load_sample_scene

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


class EncoderHarness:
    """An EncoderStage on its own thread, fed by hand: ``publish`` sets the newest reconstructed frame."""

    def __init__(self) -> None:
        from service.pipeline import DropCounter, EncoderStage, Newest, PipelineConfig
        from tests.test_service_helpers import PortReader

        self.cond, self.stop, self.drops = threading.Condition(), threading.Event(), DropCounter()
        self.published = Newest(self.cond)
        self.stage = EncoderStage(PipelineConfig(source="sim"), self.published, lambda: True, self.cond,
                                  self.drops, self.stop)
        self.readers = [PortReader(self.stage.jpeg_port).__enter__(), PortReader(self.stage.preview_port).__enter__()]
        self.jpegs, self.previews = self.readers[0].items, self.readers[1].items
        self.image = np.random.default_rng(0).uniform(1, 4000, (16, 24)).astype(np.float32)
        self.thread = threading.Thread(target=self.stage.run, daemon=True)
        self.thread.start()

    def publish(self, *seqs: int) -> None:
        """Publish frames ``seqs`` one after the other, all under the lock: the encoder sees only the last."""
        from service.pipeline import Published
        from svelive.core.frame import HdrFrame

        with self.cond:
            for seq in seqs:
                now = time.monotonic_ns()
                assert self.published.put(Published(HdrFrame(self.image, None, seq, now), seq, now)) == seq

    def wait(self, predicate, what: str) -> None:
        deadline = time.monotonic() + 10
        while not predicate():
            assert time.monotonic() < deadline, f"{what}: not_watched {self.stage.not_watched}, {self.drops.snapshot()}"
            time.sleep(0.005)

    def close(self) -> None:
        self.stop.set()
        with self.cond:
            self.cond.notify_all()
        self.thread.join(5)
        for reader in self.readers:
            reader.__exit__()


def test_frames_nobody_watched_are_not_drops():
    h = EncoderHarness()
    try:
        for seq in range(1, 21):  # 20 frames, nobody watching
            h.publish(seq)
        h.stage.watch(+1)  # an MJPEG client: it gets the newest frame at once
        h.wait(lambda: [j.hdr_seq for j in h.jpegs] == [20], "the newest frame encoded for the new watcher")
        assert h.stage.not_watched == 19 and h.drops.snapshot() == {}
        h.publish(21)
        h.wait(lambda: len(h.jpegs) == 2, "frame 21")
        h.publish(22)
        h.wait(lambda: len(h.jpegs) == 3, "frame 22")
        h.publish(23, 24, 25)  # while the encoder could not look: 23 and 24 are lost to the watcher
        h.wait(lambda: len(h.jpegs) == 4, "frame 25")
        assert [j.hdr_seq for j in h.jpegs] == [20, 21, 22, 25]
        assert h.drops.snapshot() == {"encoder_busy": 2} and h.stage.not_watched == 19
        h.stage.watch(-1)
        for seq in range(26, 31):  # nobody watches again: 26..29 not watched, 30 still open for a watcher
            h.publish(seq)
        h.wait(lambda: h.stage.not_watched == 19 + 4, "26..29 not watched")
        assert h.stage.snapshot_jpeg(timeout=10).hdr_seq == 30  # a snapshot takes the newest
        # the port keeps only the newest JPEG: let the reader take 30 before 33 replaces it
        h.wait(lambda: [j.hdr_seq for j in h.jpegs][-1:] == [30], "the JPEG of snapshot 30 read")
        h.publish(31, 32)
        h.publish(33)
        assert h.stage.snapshot_jpeg(timeout=10).hdr_seq == 33
        h.wait(lambda: [j.hdr_seq for j in h.jpegs][-1:] == [33], "the JPEG of snapshot 33 read")
        h.wait(lambda: h.stage.not_watched == 23 + 2, "31, 32 not watched")
        # an RTSP-like preview watcher: tone-mapped previews, no JPEG; its skipped frames are drops
        h.stage.watch_previews(+1)
        h.publish(34)
        h.wait(lambda: [p.hdr_seq for p in h.previews if p.signal][-1:] == [34], "preview 34")
        h.publish(35, 36)
        h.wait(lambda: [p.hdr_seq for p in h.previews if p.signal][-1:] == [36], "preview 36")
        assert h.drops.snapshot() == {"encoder_busy": 3} and h.stage.not_watched == 25
        assert [j.hdr_seq for j in h.jpegs] == [20, 21, 22, 25, 30, 33]  # no JPEG for the preview watcher
        h.stage.watch_previews(-1)
    finally:
        h.close()


def run_stage(raws, workers: int, frames: int, refresh: int = 0, camera=None):
    """The real live stage (ReconstructionStage) over ``raws`` all waiting at once (every thread has a frame to
    take), until it has published each: (its frames as published, in publishing order; its ``refresh_state()``
    after each; the stage). ``camera``: the frames' (default PATTERN and SENSOR, monochrome)."""
    from service.pipeline.calibration import Calibration
    from service.pipeline.handoff import Newest, NewestSlot
    from service.pipeline.meters import DropCounter, RateMeter
    from service.pipeline.quality import LiveQuality
    from service.pipeline.reconstruction import ReconstructionStage
    from svelive.core.camera import Camera
    from svelive.core.frame import Frame

    camera = camera if camera is not None else Camera.build(PATTERN, sensor=SENSOR)
    pixel_format = "Mono12" if camera.cfa is None else "BayerRG12"
    slot, stop, port = NewestSlot(len(raws)), threading.Event(), Newest()
    for i, raw in enumerate(raws):
        slot.put(Frame(raw=raw, frame_id=i, host_time_ns=time.monotonic_ns(), pixel_format=pixel_format,
                       camera=camera))
    published, states = [], []

    class Recorded(ReconstructionStage):
        def _publish(self, *args) -> None:  # the real stage, every frame it publishes noted
            super()._publish(*args)
            published.append(self.latest())
            states.append(self.refresh_state())

    quality = LiveQuality(default_method(True), True, "fixed")
    stage = Recorded(slot, Calibration(None, None, lambda: None, stop), quality, RateMeter(), workers, port,
                     DropCounter(), stop, frames=frames, refresh=refresh)
    thread = threading.Thread(target=stage.run)
    thread.start()
    deadline = time.monotonic() + 120
    while len(published) < len(raws) and time.monotonic() < deadline:
        time.sleep(0.05)
    stop.set()
    slot.close()
    thread.join(10)
    assert not thread.is_alive() and stage.error is None
    assert [p.hdr.frame_id for p in published] == list(range(len(raws)))  # every frame, in order
    return published, states, stage


@pytest.mark.parametrize("workers, frames", [(1, 1), (2, 1), (2, 2), (3, 3), (4, 2)])
def test_stage_reconstructs_frames_at_once_and_publishes_them_in_order(workers, frames):
    """The live stage's threads each estimate a frame and fuse in arrival order: what it publishes is
    exactly the sequential stream's output, frame for frame."""
    image = scene(0)
    disc = moving_disc(image[:96, :128], float(image.max() * 4), 12.0, (40.0, 30.0), (3.0, 5.0))
    raws = [f.raw for f in render_sequence(disc, 7, PATTERN, SENSOR, seed=4)]
    expected = [r.image for r in run_plain(raws)]
    published, _, stage = run_stage(raws, workers, frames)
    for p, image in zip(published, expected):
        np.testing.assert_array_equal(p.hdr.image, image)
    assert stage.motion_fraction == pytest.approx(float(np.count_nonzero(published[-1].hdr.motion)) / image.size)


@pytest.mark.parametrize("workers, frames", [(2, 2), (3, 3)])
def test_stage_with_band_refresh_publishes_the_sequential_streams_frames(workers, frames):
    """With ``refresh`` (a monochrome stream skipping settled bands) the stage's threads estimate frames ahead of
    their fusion, each with a band selection taken from an older history: what it publishes is still exactly
    the sequential refresh stream's output, frame for frame, and bands were skipped."""
    image = scene(0)[:256, :192]
    disc = moving_disc(image, float(image.max() * 4), 12.0, (150.0, 20.0), (0.0, 6.0))
    raws = [f.raw for f in render_sequence(disc, 22, PATTERN, SENSOR, seed=5)]
    sequential = Reconstructor(PATTERN, **KW, black_level=SENSOR.black_level, refresh=8)
    expected = [sequential.process(raw).image for raw in raws]
    published, states, _ = run_stage(raws, workers, frames, refresh=8)
    for p, want in zip(published, expected):
        np.testing.assert_array_equal(p.hdr.image, want)
    assert min(state["computed"] for state in states[10:]) < 4  # bands skipped (4 bands of 64 rows)


def test_stage_runs_the_band_refresh_on_colour_streams_too():
    """``refresh`` applies to the live stage's colour streams as to monochrome ones (``colour_refresh``): a still
    dual-ISO view (the sensor given) publishes the sequential colour refresh stream's frames, bands skipped."""
    from svelive.bench.live import case_camera, case_radiance, resized, static_frames

    camera = case_camera("dual-iso")
    view = resized(load_sample_scene("mttamwest", rgb=True), (256, 192))
    raws, _ = static_frames(case_radiance("dual-iso", "bright", view), camera, 14, 1)
    sequential = Reconstructor(camera, refresh=8, colour_refresh=True)
    expected = [sequential.process(raw).image for raw in raws]
    published, states, _ = run_stage(raws, 2, 1, refresh=8, camera=camera)
    for p, want in zip(published, expected):
        np.testing.assert_array_equal(p.hdr.image, want)
    assert states[-1]["applies"] and min(state["computed"] for state in states[9:]) < 4, states[-1]


def run_plain(raws) -> list:
    r = Reconstructor(PATTERN, white_level=SENSOR.white_level, gain=SENSOR.gain, read_noise=SENSOR.read_noise,
                      black_level=SENSOR.black_level)
    return [r.process(raw) for raw in raws]
