"""RTSP/H.264 publisher: a real RTSP client (GStreamer rtspsrc ! decodebin) on 127.0.0.1 decodes the preview.

The pipeline runs over the simulated camera of tests/test_service_helpers.py (mono) or
tests/test_service_colour.py (RGGB); the client pulls decoded frames from an appsink
with bounded waits.
"""

from __future__ import annotations

import os
import socket
import sys
import threading
import time

import cv2
import numpy as np
import pytest

from service.pipeline import Pipeline, PipelineConfig, no_signal_image
from service.publishers import rtsp
from service.publishers.rtsp import H264Settings, RtspPublisher, read_timecode, stamp_timecode, token_matches
from svelive.core.errors import SveliveError
from tests.test_service_colour import ColourSimSource, make_colour_camera
from tests.test_service_helpers import PortReader, ServerThread, SimSource, free_port, make_camera
from tests.test_service_priority import threads_priority


def _missing() -> str | None:
    try:
        Gst = rtsp.gstreamer()[0]
    except SveliveError as exc:
        return str(exc)
    for name in ("rtspsrc", "decodebin", "appsink"):
        if Gst.ElementFactory.find(name) is None:
            return f"the test client needs the GStreamer element {name} (gstreamer1.0-plugins-good/base)"
    return None


MISSING = _missing()
pytestmark = pytest.mark.skipif(MISSING is not None, reason=f"GStreamer RTSP server not installed: {MISSING}")

SHAPE = (192, 224)
TOKEN = "s3cret-token"


class RtspClientError(Exception):
    """The client's pipeline posted an error (e.g. 401 Unauthorized)."""


class RtspClient:
    """rtspsrc (RTP over TCP, no jitter buffer latency) ! decodebin ! videoconvert ! appsink: BGR, or its green
    channel for grey pictures."""

    def __init__(self, url: str, password: str | None = None, colour: bool = False, publisher=None) -> None:
        Gst = rtsp.gstreamer()[0]
        import gi

        gi.require_version("GstApp", "1.0")
        from gi.repository import GstApp  # noqa: F401 - gives the appsink its pull methods

        credentials = f" user-id=viewer user-pw={password}" if password is not None else ""
        # BGR even for grey pictures: videoconvert's I420 -> GRAY8 copies the luma plane (limited range)
        # without the range expansion of a player's I420 -> RGB
        self.colour = colour
        self.publisher = publisher
        self.pipeline = Gst.parse_launch(
            f'rtspsrc location="{url}"{credentials} protocols=tcp latency=0 ! decodebin ! videoconvert '
            '! video/x-raw,format=BGR ! appsink name=sink sync=false max-buffers=2 drop=true')
        self.sink = self.pipeline.get_by_name("sink")
        self.pipeline.set_state(Gst.State.PLAYING)

    def frames(self, n: int, timeout: float = 30.0) -> list[np.ndarray]:
        """The next ``n`` decoded frames as uint8 (H, W) or (H, W, 3); RtspClientError if the pipeline fails,
        AssertionError when they do not come within ``timeout`` s."""
        Gst = rtsp.gstreamer()[0]
        out: list[np.ndarray] = []
        deadline = time.monotonic() + timeout
        while len(out) < n:
            message = self.pipeline.get_bus().pop_filtered(Gst.MessageType.ERROR)
            if message is not None:
                error, debug = message.parse_error()
                raise RtspClientError(f"{error.message} {debug}")
            if time.monotonic() > deadline:
                _, state, _ = self.pipeline.get_state(0)
                raise AssertionError(f"{len(out)} of {n} frames in {timeout} s; client pipeline {state.value_nick}; "
                                     f"server {self.publisher.state() if self.publisher else '?'}")
            sample = self.sink.try_pull_sample(Gst.SECOND // 5)
            if sample is not None:
                out.append(self._array(sample))
        return out

    def _array(self, sample) -> np.ndarray:
        Gst = rtsp.gstreamer()[0]
        caps = sample.get_caps().get_structure(0)
        width, height = caps.get_value("width"), caps.get_value("height")
        ok, info = sample.get_buffer().map(Gst.MapFlags.READ)
        assert ok
        try:
            data = np.frombuffer(info.data, np.uint8).copy()
        finally:
            sample.get_buffer().unmap(info)
        stride = data.size // height  # rows are padded to 4 bytes
        image = data[:stride * height].reshape(height, stride)[:, :width * 3].reshape(height, width, 3)
        return image if self.colour else image[..., 1].copy()

    def close(self) -> None:
        Gst = rtsp.gstreamer()[0]
        self.pipeline.set_state(Gst.State.NULL)

    def __enter__(self) -> RtspClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def wait_until(predicate, timeout: float = 30.0, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"{what} not reached in {timeout} s")
        time.sleep(0.05)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(cv2.PSNR(a, b))


@pytest.fixture
def mono_pipeline():
    # one raw repeated: every reconstructed frame and its preview are the same picture
    camera = make_camera(fps=20.0, n=1, shape=SHAPE)
    pipeline = Pipeline(PipelineConfig(source="sim", temporal=False), lambda: SimSource(camera))
    with pipeline:
        # a client that comes before the first frame gets a media of the no-signal size (640x360)
        wait_until(lambda: pipeline.latest() is not None, timeout=60, what="the first frame")
        yield pipeline


def test_no_client_no_encoding_then_a_client_decodes_the_preview(mono_pipeline):
    pipeline = mono_pipeline
    with RtspPublisher(pipeline, host="127.0.0.1", port=0) as publisher:
        assert publisher.url == f"rtsp://127.0.0.1:{publisher.port}/live" and publisher.port > 0
        wait_until(lambda: pipeline.reconstructed.count >= 8, what="8 reconstructed frames")
        state = publisher.state()
        # nobody watches: nothing tone-mapped, nothing JPEG- or H.264-encoded
        assert state["frames_pushed"] == 0 and state["frames_encoded"] == 0 and not state["encoding"]
        assert pipeline.encoder.previews.count == 0 and pipeline.encoder.encoded.count == 0
        with RtspClient(publisher.url, publisher=publisher) as client:
            frames = client.frames(8)
            state = publisher.state()
            assert state["clients"] == 1 and state["encoding"] and (state["width"], state["height"]) == SHAPE[::-1]
            assert state["frames_encoded"] >= 8 and state["fps"] > 0 and state["bitrate_kbps"] > 0
            preview = pipeline.encoder.latest_preview()
        assert all(frame.shape == SHAPE for frame in frames)
        assert preview.image.shape == SHAPE
        assert psnr(frames[-1], preview.image) > 30  # the picture itself, through H.264
        # RTSP alone: the tone map ran, no JPEG was made
        assert pipeline.encoder.encoded.count == 0 and pipeline.encoder.previews.count >= 8
        # the client left: the media goes, and encoding stops
        wait_until(lambda: not publisher.state()["encoding"] and publisher.state()["clients"] == 0,
                   what="the media torn down after the client left")
        encoded, previews = publisher.state()["frames_encoded"], pipeline.encoder.previews.count
        reconstructed = pipeline.reconstructed.count
        wait_until(lambda: pipeline.reconstructed.count >= reconstructed + 6, what="6 more frames")
        assert publisher.state()["frames_encoded"] == encoded and pipeline.encoder.previews.count == previews
        assert pipeline.encoder.preview_watchers == 0


def test_one_encoding_shared_by_two_clients_and_with_mjpeg(mono_pipeline):
    pipeline = mono_pipeline
    with PortReader(pipeline.preview_port) as preview_reader, PortReader(pipeline.jpeg_port) as jpeg_reader, \
            RtspPublisher(pipeline, host="127.0.0.1", port=0) as publisher:
        previews, jpegs = preview_reader.items, jpeg_reader.items
        pipeline.watch(+1)  # an MJPEG client
        try:
            with RtspClient(publisher.url, publisher=publisher) as first, RtspClient(publisher.url, publisher=publisher) as second:
                assert all(f.shape == SHAPE for f in first.frames(5) + second.frames(5))
                state = publisher.state()
        finally:
            pipeline.watch(-1)
    assert state["clients"] == 2 and publisher.medias == 1  # one shared media, one encoder
    assert state["frames_encoded"] <= state["frames_pushed"]
    # one tone map per frame for both: as many tone maps as distinct frames sent as JPEG or preview
    preview_seqs = [p.hdr_seq for p in previews if p.signal]
    assert len(preview_seqs) == len(set(preview_seqs)) > 0
    both = set(preview_seqs) & {j.hdr_seq for j in jpegs if j.signal}
    assert len(both) >= 3  # frames that went to both publishers
    wait_until(lambda: pipeline.encoder.previews.count == len({p.hdr_seq for p in previews if p.signal}
                                                               | {j.hdr_seq for j in jpegs if j.signal}),
               timeout=5, what="one tone map per frame")


def test_a_late_joiner_gets_a_keyframe_at_once(mono_pipeline):
    # a keyframe every 60 s: without the key unit forced for it, the second client would wait for 1200 frames
    with RtspPublisher(mono_pipeline, host="127.0.0.1", port=0, settings=H264Settings(keyframe_s=60)) as publisher, \
            RtspClient(publisher.url, publisher=publisher) as first:
        first.frames(10)
        with RtspClient(publisher.url, publisher=publisher) as second:
            assert second.frames(2, timeout=20)[0].shape == SHAPE
        assert publisher.medias == 1


@pytest.mark.skipif(sys.platform != "linux", reason="threads have priorities of their own on Linux only")
def test_the_publishers_threads_run_below_the_reconstruction(mono_pipeline):
    base, steps = os.getpriority(os.PRIO_PROCESS, os.getpid()), mono_pipeline.config.publisher_nice
    assert steps > 0 and base + steps <= 19  # the default lowers them
    assert not mono_pipeline.config.publisher_idle  # and keeps the normal policy (EncoderPriority: its own tests)
    mono_pipeline.watch(+1)  # an MJPEG client: the encoder thread makes JPEGs too
    try:
        # two x264 threads asked for: they must inherit the streaming thread's priority
        with RtspPublisher(mono_pipeline, host="127.0.0.1", port=0, settings=H264Settings(threads=2)) as publisher, \
                RtspClient(publisher.url, publisher=publisher) as client:
            client.frames(3)
            threads = threads_priority()
            python = {t.name: t.native_id for t in threading.enumerate()}
    finally:
        mono_pipeline.watch(-1)
    for name in ("svelive-capture", "svelive-reconstruct"):
        assert threads[python[name]][1:] == (base, False), name
    assert threads[python["svelive-encode"]][1:] == (base + steps, False)
    assert mono_pipeline.encoder.priority.public() == {"nice": base + steps, "idle_asked": False, "idle": False,
                                                       "idle_fallbacks": 0}
    assert threads[python["svelive-rtsp-push"]][1:] == (base + steps, False)
    # the media's streaming thread and x264's threads: GStreamer names them after the appsrc's pad
    streaming = [priority for name, *priority in threads.values() if name == "src:src"]
    assert len(streaming) >= 3 and set(map(tuple, streaming)) == {(base + steps, False)}


def test_colour_preview_is_served_in_colour():
    camera = make_colour_camera(fps=15.0, n=1)
    with Pipeline(PipelineConfig(source="sim", temporal=False), lambda: ColourSimSource(camera)) as pipeline:
        wait_until(lambda: pipeline.reconstructed.count >= 2, timeout=60, what="2 reconstructed colour frames")
        with RtspPublisher(pipeline, host="127.0.0.1", port=0) as publisher, \
                RtspClient(publisher.url, colour=True, publisher=publisher) as client:
            frames = client.frames(8)
            preview = pipeline.encoder.latest_preview()
    assert preview.image.shape == SHAPE + (3,)
    assert all(frame.shape == SHAPE + (3,) for frame in frames)
    assert psnr(frames[-1], preview.image) > 30
    # the colour survived: the decoded frame's chroma follows the preview's, far from a grey picture
    grey = cv2.cvtColor(cv2.cvtColor(preview.image, cv2.COLOR_BGR2GRAY), cv2.COLOR_GRAY2BGR)
    assert psnr(frames[-1], preview.image) > psnr(frames[-1], grey) + 3


def test_token_is_required_as_basic_password_or_query(mono_pipeline):
    with RtspPublisher(mono_pipeline, host="127.0.0.1", port=0, token=TOKEN) as publisher:
        for url, password in ((publisher.url, None), (publisher.url, "wrong"), (publisher.url + "?token=wrong", None),
                              (publisher.url + "?token=" + TOKEN[:-1], None)):
            with RtspClient(url, password, publisher=publisher) as client, pytest.raises(RtspClientError, match="Unauthorized"):
                client.frames(1)
        assert publisher.state()["frames_pushed"] == 0 and publisher.medias == 0  # a refused client costs nothing
        for url, password in ((publisher.url, TOKEN), (publisher.url + "?token=" + TOKEN, None)):
            with RtspClient(url, password, publisher=publisher) as client:
                assert client.frames(2)[0].shape == SHAPE
        assert publisher.state()["auth"]


def test_token_matches():
    basic = "Basic " + __import__("base64").b64encode(b"anyone:" + TOKEN.encode()).decode()
    assert token_matches(TOKEN, basic, None)
    assert token_matches(TOKEN, None, "a=1&token=" + TOKEN)
    assert not token_matches(TOKEN, basic.replace("Basic", "Digest"), None)
    assert not token_matches(TOKEN, "Basic !!notbase64", "token=x")
    assert not token_matches(TOKEN, None, None)
    assert not token_matches(TOKEN, "Basic " + __import__("base64").b64encode(TOKEN.encode()).decode(), None)


def test_stop_disconnects_clients_and_frees_the_port(mono_pipeline):
    publisher = RtspPublisher(mono_pipeline, host="127.0.0.1", port=0).start()
    port = publisher.port
    with RtspClient(publisher.url, publisher=publisher) as client:
        client.frames(2)
        publisher.stop()
        assert publisher.server._thread is None
        assert mono_pipeline.encoder.preview_watchers == 0
        with pytest.raises((RtspClientError, AssertionError)):
            client.frames(200, timeout=5)  # the server went away: an error, or at least no 200 more frames
    again = RtspPublisher(mono_pipeline, host="127.0.0.1", port=port).start()
    again.stop()
    publisher.stop()  # idempotent


def test_bad_settings_are_refused(mono_pipeline):
    with pytest.raises(SveliveError, match="path"):
        RtspPublisher(mono_pipeline, path="live")
    with pytest.raises(SveliveError, match="port"):
        RtspPublisher(mono_pipeline, port=70000)
    with pytest.raises(SveliveError, match="preset"):
        H264Settings(speed_preset="placebo-ish")
    with pytest.raises(SveliveError, match="fps"):
        H264Settings(fps=0)
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        with pytest.raises(SveliveError, match="cannot listen for RTSP"):
            RtspPublisher(mono_pipeline, host="127.0.0.1", port=busy.getsockname()[1]).start()


def test_launch_description_is_low_latency():
    text = rtsp.launch_description(1920, 1200, H264Settings())
    for part in ("tune=zerolatency", "bframes=0", "key-int-max=30", "speed-preset=ultrafast", "leaky-type=downstream",
                 "max-buffers=1", "format=I420", "width=1920", "height=1200", "stream-format=byte-stream",
                 "config-interval=0"):
        assert part in text
    assert f"bitrate={rtsp.bitrate_kbps(1920, 1200, 30.0)}" in text
    assert rtsp.bitrate_kbps(1920, 1200, 30.0) > rtsp.bitrate_kbps(1280, 720, 30.0) > rtsp.bitrate_kbps(64, 64, 1)
    assert "key-int-max=10" in rtsp.launch_description(640, 480, H264Settings(keyframe_s=0.5, fps=20))


def test_running_time_is_zero_until_the_base_time_is_set():
    assert rtsp.running_time_ns(5_000_000_000, 4_000_000_000) == 1_000_000_000
    assert rtsp.running_time_ns(5_000_000_000, 0) == 0  # the clock came, the base time not yet
    assert rtsp.running_time_ns(5_000_000_000, 6_000_000_000) == 0


def test_a_frame_pushed_between_the_clock_and_the_base_time_is_stamped_near_zero():
    # The window of the PAUSED -> PLAYING change in which appsrc has the clock but a base time of 0: appsrc's
    # do-timestamp stamped such a frame with the clock's absolute time (the uptime), and the stream's
    # synchronised sink held it, and the stream, until then.
    Gst = rtsp.gstreamer()[0]
    pipeline = Gst.Pipeline.new("t")
    pipeline.add(Gst.parse_launch(rtsp.launch_description(64, 48, H264Settings())))
    src, encoder = pipeline.get_by_name("src"), pipeline.get_by_name("enc")
    stamps: list[int] = []

    def seen(pad, info):
        stamps.append(info.get_buffer().pts)
        return Gst.PadProbeReturn.OK

    encoder.get_static_pad("sink").add_probe(Gst.PadProbeType.BUFFER, seen)
    clock = Gst.SystemClock.obtain()
    assert clock.get_time() > Gst.SECOND  # else an absolute stamp could not be told from a running time
    src.set_clock(clock)
    assert src.get_base_time() == 0
    rtsp.push_frame(src, bytes(64 * 48 * 3 // 2))
    pipeline.set_state(Gst.State.PLAYING)
    try:
        wait_until(lambda: stamps, timeout=10, what="the frame at the encoder")
    finally:
        pipeline.set_state(Gst.State.NULL)
    assert 0 <= stamps[0] < Gst.SECOND


def test_i420_of_grey_and_colour():
    rng = np.random.default_rng(3)
    # uniform 2x2 blocks: 4:2:0 keeps them; what is left is the rounding of the limited range
    bgr = np.repeat(np.repeat(rng.integers(30, 226, (24, 32, 3), dtype=np.uint8), 2, 0), 2, 1)
    back = cv2.cvtColor(rtsp.to_i420(bgr), cv2.COLOR_YUV2BGR_I420)
    assert np.abs(back.astype(int) - bgr).max() <= 3
    grey = rng.integers(0, 256, (48, 64), dtype=np.uint8)
    i420 = rtsp.to_i420(grey)
    assert i420.shape == (72, 64) and (i420[48:] == 128).all()
    assert i420[:48].min() >= 16 and i420[:48].max() <= 235
    restored = cv2.cvtColor(i420, cv2.COLOR_YUV2BGR_I420)[..., 1].astype(int)
    assert np.abs(restored - grey).max() <= 1  # a decoder's limited -> full range gives the grey back


def test_timecode_survives_lossy_coding():
    rng = np.random.default_rng(1)
    for shape in ((120, 400), (120, 400, 3)):
        image = rng.integers(0, 256, shape, dtype=np.uint8)
        value = int(time.time() * 1000)
        stamp_timecode(image, value)
        ok, jpeg = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 40])
        assert ok
        assert read_timecode(cv2.imdecode(jpeg, cv2.IMREAD_UNCHANGED)) == value


def test_no_signal_frames_while_the_source_is_offline():
    camera = make_camera(fps=20.0, n=1, shape=SHAPE)
    config = PipelineConfig(source="sim", temporal=False, offline_after_s=0.6, retry_s=0.2, no_signal_fps=5.0)
    with Pipeline(config, lambda: SimSource(camera)) as pipeline, \
            RtspPublisher(pipeline, host="127.0.0.1", port=0) as publisher:
        wait_until(lambda: pipeline.latest() is not None, timeout=60, what="the first frame")
        with RtspClient(publisher.url, publisher=publisher) as client:
            live = client.frames(3)[-1]
            camera.paused = True
            wait_until(lambda: not pipeline.online(), what="the source offline")
            frames = client.frames(4, timeout=30)  # the stream goes on, at the no-signal rate
        assert all(frame.shape == SHAPE for frame in frames)
        no_signal = no_signal_image(SHAPE[1], SHAPE[0])
        assert psnr(frames[-1], no_signal) > 25 and psnr(live, no_signal) < 20


def test_two_cameras_on_one_port_and_a_path_alias_shares_the_camera_encoding(mono_pipeline):
    from service.publishers.rtsp import RtspServer

    small = (96, 128)
    other = Pipeline(PipelineConfig(source="sim", temporal=False), lambda: SimSource(make_camera(fps=20.0, n=1,
                                                                                                shape=small)))
    with other:
        wait_until(lambda: other.latest() is not None, timeout=60, what="the second camera's first frame")
        server = RtspServer(host="127.0.0.1", port=0, token=TOKEN)
        first = RtspPublisher(mono_pipeline, server=server, path="/cam/one", aliases=("/live",))
        second = RtspPublisher(other, server=server, path="/cam/two")
        with pytest.raises(SveliveError, match="served twice"):
            RtspPublisher(other, server=server, path="/live")
        with server:
            assert first.port == second.port == server.port and first.url.endswith("/cam/one")
            with RtspClient(first.url, TOKEN, publisher=first) as a, \
                    RtspClient(server.url("/live"), TOKEN, publisher=first) as b, \
                    RtspClient(second.url, TOKEN, publisher=second) as c:
                assert all(f.shape == SHAPE for f in a.frames(3) + b.frames(3))
                assert all(f.shape == small for f in c.frames(3))
                assert first.state()["clients"] == 2 and second.state()["clients"] == 1
            assert first.medias == 1 and second.medias == 1  # both paths of the first camera: one encoding
        assert server._thread is None


def test_the_app_serves_rtsp_from_its_lifespan_and_frees_the_port_when_it_stops():
    """``serve --rtsp``: the app's lifespan makes the RTSP server (every camera at /cam/NAME, the first also at
    /live), starts it before the pipelines and stops it with the server, as it does the MJPEG fan-out."""
    rtsp_port = free_port()
    said = []  # the frames the server encoded
    with ServerThread(make_camera(fps=20.0, n=1, shape=SHAPE), server={"rtsp_port": rtsp_port}) as server:
        assert server.app.state.rtsp.port == rtsp_port
        state = server.state()["rtsp"]
        assert state["url"] == f"rtsp://127.0.0.1:{rtsp_port}/cam/main" and "/live" in state["paths"]
        with RtspClient(f"rtsp://127.0.0.1:{rtsp_port}/live") as client:
            assert all(frame.shape == SHAPE for frame in client.frames(3))
        said.append(server.state()["rtsp"]["frames_encoded"])
    assert said[0] >= 3
    rtsp.check_port("127.0.0.1", rtsp_port)  # stopped with the server: the port is free again
