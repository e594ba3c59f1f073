"""The live service under load: replayed 1920x1200 12-bit frames at 30 fps, 10 MJPEG clients.

    python benchmarks/service.py [--minutes 10] [--clients 10] [--fps 30] [--idle-s 15] [--method weighted]
                                 [--no-temporal] [--workers N] [--parallel-frames N] [--scene pan|static]
                                 [--size 1920x1200]
                                 [--cfa none|RGGB] [--rtsp] [--live-quality fixed|adaptive] [--replay fed|held]
                                 [--refresh K] [--publisher-nice N] [--publisher-idle on|off]

Runs ``svelive serve``'s app (real uvicorn) in a child process, its kernels prepared as
``svelive serve`` prepares them (``warm_up_kernels``: compiled into numba's cache by a process
of their own, loaded by the server; the wait for the first frames starts after it), over a source
that replays pre-rendered demo frames (1920x1200, 12-bit; ``--cfa none``, the
default: monochrome, pattern 1,4/16,64; ``--cfa RGGB``: the colour demo camera,
a Bayer mosaic with its dual-ISO exposures, labelled BayerRG12) at the target rate (``--scene pan``: the demo's camera pans, so every frame moves
and temporal fusion restarts each frame; ``static``: the same view, new noise in
every frame, so fusion runs on every pixel). The 24 frames are rendered once by a
feeder process and copied through a pipe into a new buffer of the server's for each
frame it takes, as a camera's driver delivers them (``--replay held``: the server
process holds the 24 frames itself, about 110 MB of its resident memory at
1920x1200, and hands out the same arrays again). Then, from this process:

1. no client for ``--idle-s`` s: the server's CPU use (encoding is off when nobody watches);
2. ``--clients`` MJPEG clients for ``--minutes`` minutes: captured / reconstructed /
   streamed fps, drops by cause, latency from frame arrival to the part received by a
   client (X-Timestamp vs the receive time, same host clock) p50 / p95, the
   server's own arrival-to-sent latency, and its resident memory every 10 s (growth
   from the end of the first minute to the end; VmRSS, in MiB) and at its peak over the
   measured part of the phase (VmHWM, whose record is restarted as that part starts), and the peak before
   it (the start-up's: the kernels loaded, the first frames, the idle phase), and the kernels the server compiled
   itself rather than loaded from numba's cache (a server that compiles keeps LLVM's memory: such a run's memory
   is not comparable).

The clients run in this process (asyncio, headers parsed, bodies skipped) and
so share the machine's cores with the server; on a real deployment they are
elsewhere.

``--rtsp``: the server also publishes RTSP/H.264 (service/publishers/rtsp.py) with
a timecode (the frame's arrival time in ms, written as 48 black/white 8x8 squares
into the top-left corner of every RTSP frame), and phase 2 runs three times in
the same server, ``--minutes`` each: the MJPEG clients alone, the MJPEG clients
and one RTSP client (GStreamer rtspsrc over TCP, jitter buffer 0 ms, decoded by
avdec_h264 in this process), and the RTSP client alone. The RTSP latency is
"arrival -> frame decoded by the client": the decode time (Unix clock) minus the
timecode read back from the decoded picture, on the same host clock.
"""

from __future__ import annotations

import argparse
import asyncio
import fcntl
import json
import os
import pickle
import re
import platform
import socket
import subprocess
import sys
import threading
import time
import urllib.request

import numpy as np

# Run as a script, this file's directory comes first on sys.path and its own name
# would hide the ``service`` package.
_HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or ".") != _HERE]
sys.path.insert(0, os.path.dirname(_HERE))  # this checkout, not an editable install's


def render_replay(fps: float, width: int, height: int, n: int = 24, static: bool = False,
                  cfa: str = "none") -> tuple[list[np.ndarray], str, object]:
    """The n demo frames the replay cycles through (uint16 (height, width) raw arrays), their pixel format label
    and their camera. ``static``: the demo's pan is stopped (a still view, independent noise in every frame).
    ``cfa``: ``"none"`` for the monochrome demo, else the colour filter of the colour demo."""
    from svelive.capture.demo import DemoSource

    demo = DemoSource("demo", width=width, height=height, fps=0, period_s=1e9 if static else n / fps * 4, cfa=cfa)
    rendered = list(demo.frames(limit=n))
    demo.close()
    return [f.raw for f in rendered], rendered[0].pixel_format, rendered[0].camera


class FrameFeed:
    """The replay's frames from a feeder process (``--feed``) through a pipe: frame k on request, into a buffer
    of this process's own, as a camera's frames come from its driver; the feeder holds the rendered frames, so
    this process holds only the frames in flight. One frame is requested ahead (the pipe holds it)."""

    def __init__(self, fps: float, width: int, height: int, n: int, static: bool, cfa: str) -> None:
        self._process = subprocess.Popen(
            [sys.executable, __file__, "--feed", str(n), "--fps", str(fps), "--size", f"{width}x{height}",
             "--scene", "static" if static else "pan", "--cfa", cfa], stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        self._out = self._process.stdout.fileno()
        try:  # room for a whole frame in the pipe: the feeder writes the frame asked ahead at once
            fcntl.fcntl(self._out, getattr(fcntl, "F_SETPIPE_SZ", 1031), width * height * 2)
        except OSError:
            pass
        size = int.from_bytes(self._read(bytearray(8)), "little")
        self.label, self.camera, self.dtype = pickle.loads(self._read(bytearray(size)))
        self.shape = (height, width)
        self._pending: int | None = None

    def _read(self, buffer: bytearray | memoryview) -> bytearray | memoryview:
        view, done = memoryview(buffer).cast("B"), 0
        while done < len(view):
            got = os.readv(self._out, [view[done:]])
            if got == 0:
                raise EOFError("the frame feeder stopped")
            done += got
        return buffer

    def _ask(self, k: int) -> None:
        self._process.stdin.write(k.to_bytes(4, "little"))
        self._process.stdin.flush()
        self._pending = k

    def frame(self, k: int, then: int) -> np.ndarray:
        """Frame ``k`` (uint (H, W), a new array), asking for frame ``then`` next."""
        if self._pending is not None and self._pending != k:  # (a new Replay starts again at 0)
            self._read(np.empty(self.shape, self.dtype))
            self._pending = None
        if self._pending is None:
            self._ask(k)
        raw = self._read(np.empty(self.shape, self.dtype))
        self._ask(then)
        return raw


def feed(fps: float, width: int, height: int, n: int, static: bool, cfa: str) -> None:
    """The feeder process (``--feed n``): renders the replay's frames (:func:`render_replay`), writes their
    label, camera and dtype (pickled, after its length), then frame k for each index k read from stdin."""
    raws, label, camera = render_replay(fps, width, height, n, static, cfa)
    out, requests = sys.stdout.buffer, sys.stdin.buffer
    header = pickle.dumps((label, camera, raws[0].dtype))
    out.write(len(header).to_bytes(8, "little") + header)
    out.flush()
    try:
        while len(k := requests.read(4)) == 4:  # until the server goes (its end of the pipe closes)
            out.write(memoryview(raws[int.from_bytes(k, "little")]).cast("B"))
            out.flush()
    except BrokenPipeError:
        pass


def replay_source_factory(fps: float, width: int, height: int, n: int = 24, static: bool = False,
                          cfa: str = "none", fed: bool = False):
    """A factory of Sources replaying n pre-rendered demo frames (:func:`render_replay`) at ``fps`` (fresh
    timestamps), frame k of a source being the (k mod n)-th.

    ``fed``: the frames come from a feeder process (:class:`FrameFeed`), copied into a new array each, as a
    camera delivers them; else this process holds the n frames and hands them out themselves.
    """
    from svelive.capture import Source
    from svelive.core.frame import Frame

    if fed:
        source = FrameFeed(fps, width, height, n, static, cfa)
        label, camera = source.label, source.camera

        def raw_of(k: int) -> np.ndarray:
            return source.frame(k % n, (k + 1) % n)
    else:
        raws, label, camera = render_replay(fps, width, height, n, static, cfa)

        def raw_of(k: int) -> np.ndarray:
            return raws[k % n]

    class Replay(Source):
        poll_s = 0.05

        def __init__(self) -> None:
            super().__init__("bench-replay")
            self.camera = camera
            self._n = 0
            self._t0 = 0.0

        def _open(self) -> None:
            self._t0 = time.monotonic()

        def _next(self):
            due = self._t0 + self._n / fps
            if not self._wait(min(due - time.monotonic(), self.poll_s)) or time.monotonic() < due:
                return None
            if time.monotonic() - due > 1.0:  # far behind: restart the clock rather than burst
                self._t0 = time.monotonic() - self._n / fps
            frame = Frame(raw=raw_of(self._n), frame_id=self._n, host_time_ns=time.monotonic_ns(),
                          pixel_format=label, camera=self.camera)
            self._n += 1
            return frame

    return Replay


def serve(port: int, fps: float, method: str | None, temporal: bool, workers: int, static: bool,
          size: tuple[int, int], cfa: str, rtsp_port: int = 0, parallel_frames: int = 1,
          live_quality: str = "fixed", fed: bool = True, refresh: int | None = None,
          publisher_nice: int | None = None, publisher_idle: bool | None = None) -> None:
    """Child process: the service over the replay source (and RTSP on ``rtsp_port`` when given, its state at
    ``/bench/rtsp``); ``fed``: its frames from a feeder process (:func:`replay_source_factory`); ``refresh``:
    ``PipelineConfig.refresh``, ``publisher_nice`` and ``publisher_idle``: the same settings of
    ``PipelineConfig``, None: the checkout's default."""
    import uvicorn

    from service.app import create_app, listen_socket
    from service.pipeline import Pipeline, PipelineConfig
    from service.settings import ServerSettings

    try:  # what svelive serve does at start-up (absent from checkouts before it)
        from svelive.memory import keep_freed_memory
        keep_freed_memory()
    except ImportError:
        pass
    factory = replay_source_factory(fps, size[0], size[1], static=static, cfa=cfa, fed=fed)
    extra = {name: value for name, value in (("refresh", refresh), ("publisher_nice", publisher_nice),
                                             ("publisher_idle", publisher_idle)) if value is not None}
    pipeline = Pipeline(PipelineConfig(source="bench-replay", method=method, temporal=temporal, workers=workers,
                                       parallel_frames=parallel_frames, live_quality=live_quality, **extra), factory)
    settings = ServerSettings(port=port, log_level="warning")
    sock = listen_socket(settings)
    try:  # the kernels as svelive serve prepares them (compiled in a child process where the checkout does)
        from service.commands import warm_up_kernels
        app = create_app(pipeline, settings, warm_up=lambda: warm_up_kernels("bench server"))
    except ImportError:
        app = create_app(pipeline, settings)
    publisher = None
    if rtsp_port:
        from service.publishers.rtsp import H264Settings, RtspPublisher

        publisher = RtspPublisher(pipeline, host="127.0.0.1", port=rtsp_port, settings=H264Settings(fps=fps),
                                  timecode=True).start()
        app.add_api_route("/bench/rtsp", publisher.state)
    app.add_api_route("/bench/threads", thread_names)
    compiled = record_compiles()
    app.add_api_route("/bench/compiles", lambda: compiled)
    print("ready", flush=True)
    try:
        uvicorn.Server(uvicorn.Config(app, log_level="warning", timeout_graceful_shutdown=1)).run(sockets=[sock])
    finally:
        if publisher is not None:
            publisher.stop()


def record_compiles() -> list[str]:
    """From now on, the qualified name of every kernel this process compiles (numba's ``numba:compile`` event: a
    kernel loaded from numba's cache is not one) appended to the list returned. A server that compiles keeps
    LLVM's memory (``svelive.jit.compile_elsewhere``): its resident memory is then not the others'."""
    from numba.core import event

    compiled: list[str] = []

    class Compiles(event.Listener):
        def on_start(self, ev: event.Event) -> None:
            pass

        def on_end(self, ev: event.Event) -> None:
            compiled.append(getattr(ev.data["dispatcher"].py_func, "__qualname__", "?"))

    event.register("numba:compile", Compiles())
    return compiled


def thread_names() -> dict[str, str]:
    """The bench server's Python threads by native id (for :func:`thread_cpu_seconds`)."""
    return {str(t.native_id): t.name for t in threading.enumerate()}


def thread_cpu_seconds(pid: int) -> dict[str, float]:
    """CPU seconds of each thread (task) of process ``pid`` so far, by native id."""
    out = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:  # the thread ended
            continue
        out[tid] = (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return out


def cpu_by_role(start: dict[str, float], end: dict[str, float], names: dict[str, str], frames: int) -> dict:
    """CPU ms per reconstructed frame of each role of the server's threads between two
    :func:`thread_cpu_seconds` readings: threads named alike (a pool's ``svelive-strip_0``, ``_1``) summed,
    threads Python does not know (native libraries' own) as ``native``."""
    roles: dict[str, float] = {}
    for tid, seconds in end.items():
        name = names.get(tid, "native")
        role = re.sub(r"(_\d+)+$", "", name)
        roles[role] = roles.get(role, 0.0) + seconds - start.get(tid, 0.0)
    return {role: round(1e3 * seconds / max(frames, 1), 1)
            for role, seconds in sorted(roles.items(), key=lambda kv: -kv[1]) if seconds > 0}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def get_state(port: int) -> dict:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/state", timeout=10) as r:
        return json.load(r)


def reset_peak_rss(pid: int) -> bool:
    """Restart the kernel's record of the process's peak resident memory (VmHWM); False where it cannot."""
    try:
        with open(f"/proc/{pid}/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def peak_rss_mb(pid: int) -> float | None:
    """The process's peak resident memory (VmHWM) in MiB, as its state's ``rss_mb``; None where not told."""
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return round(int(line.split()[1]) / 1024, 1)
    return None


def cpu_seconds(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


async def client(port: int, latencies: list[float], counts: list[int], index: int, stop: asyncio.Event) -> None:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(b"GET /stream.mjpg HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
    await writer.drain()
    await reader.readuntil(b"\r\n\r\n")  # response headers
    try:
        while not stop.is_set():
            head = await reader.readuntil(b"\r\n\r\n")
            received = time.time()
            headers = dict(line.split(": ", 1) for line in head.decode().split("\r\n")[1:] if ": " in line)
            await reader.readexactly(int(headers["Content-Length"]) + 2)
            if headers.get("X-Signal") == "live":
                latencies.append((received - float(headers["X-Timestamp"])) * 1e3)
                counts[index] += 1
    finally:
        writer.close()


class RtspReader:
    """One RTSP client on a thread of this process: rtspsrc (RTP over TCP, jitter buffer 0 ms) ! decodebin !
    GRAY8 appsink; each decoded frame's latency is its decode time minus the arrival time in its timecode."""

    def __init__(self, url: str) -> None:
        import gi

        from service.publishers.rtsp import gstreamer

        gi.require_version("GstApp", "1.0")
        from gi.repository import GstApp  # noqa: F401 - the appsink's pull methods

        del GstApp

        self.Gst = gstreamer()[0]
        self.pipeline = self.Gst.parse_launch(
            f"rtspsrc location={url} protocols=tcp latency=0 ! decodebin ! videoconvert ! video/x-raw,format=GRAY8 "
            "! appsink name=sink sync=false max-buffers=1 drop=true")
        self.sink = self.pipeline.get_by_name("sink")
        self.latencies: list[float] = []
        self.frames = 0
        self.error: str | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> RtspReader:
        self.pipeline.set_state(self.Gst.State.PLAYING)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self.pipeline.set_state(self.Gst.State.NULL)

    def _run(self) -> None:
        from service.publishers.rtsp import TIMECODE_BLOCK, read_timecode

        Gst = self.Gst
        while not self._stop.is_set():
            message = self.pipeline.get_bus().pop_filtered(Gst.MessageType.ERROR)
            if message is not None:
                self.error = message.parse_error()[0].message
                return
            sample = self.sink.try_pull_sample(Gst.SECOND // 5)
            if sample is None:
                continue
            received_ms = time.time() * 1000
            caps = sample.get_caps().get_structure(0)
            width, height = caps.get_value("width"), caps.get_value("height")
            buffer = sample.get_buffer()
            ok, info = buffer.map(Gst.MapFlags.READ)
            if not ok:
                continue
            try:
                data = np.frombuffer(info.data, np.uint8)
            finally:
                buffer.unmap(info)
            stride = data.size // height
            stamped = read_timecode(data[:stride * TIMECODE_BLOCK].reshape(TIMECODE_BLOCK, stride)[:, :width])
            latency = received_ms - stamped
            self.frames += 1
            if 0 <= latency < 10_000:  # no-signal frames carry no timecode
                self.latencies.append(latency)


def get_json(port: int, path: str) -> dict:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}{path}", timeout=10) as r:
        return json.load(r)


def percentiles(values: list[float]) -> dict:
    if not values:
        return {"p50": None, "p95": None, "n": 0}
    return {"p50": round(float(np.percentile(values, 50)), 1), "p95": round(float(np.percentile(values, 95)), 1),
            "n": len(values)}


async def load_phase(port: int, pid: int, n_clients: int, seconds: float, rtsp_url: str | None = None) -> dict:
    """``n_clients`` MJPEG clients (and one RTSP client if ``rtsp_url``) for ``seconds`` (the first 5 s not
    measured): fps, drops, latencies, CPU of the server and of this process (the clients), memory."""
    latencies: list[float] = []
    counts = [0] * n_clients
    stop = asyncio.Event()
    tasks = [asyncio.create_task(client(port, latencies, counts, i, stop)) for i in range(n_clients)]
    reader = RtspReader(rtsp_url).start() if rtsp_url else None
    rss: list[tuple[float, float]] = []
    t0 = time.monotonic()
    await asyncio.sleep(5)  # warm-up
    start_state, start_cpu, start_t = get_state(port), cpu_seconds(pid), time.monotonic()
    start_threads = thread_cpu_seconds(pid)
    start_own, start_rtsp = sum(os.times()[:2]), get_json(port, "/bench/rtsp") if rtsp_url else None
    start_counts, start_rtsp_frames = list(counts), reader.frames if reader else 0
    latencies.clear()
    if reader:
        reader.latencies.clear()
    before = peak_rss_mb(pid)  # the start-up's peak: the kernels loaded, the first frames, the phases before
    peak_from = reset_peak_rss(pid)  # the phase's own peak, not the start-up's
    while time.monotonic() - t0 < seconds:
        await asyncio.sleep(10)
        rss.append((time.monotonic() - t0, get_state(port)["server"]["rss_mb"]))
    if not rss:
        rss.append((time.monotonic() - t0, get_state(port)["server"]["rss_mb"]))
    end_state, end_cpu, end_t = get_state(port), cpu_seconds(pid), time.monotonic()
    end_threads = thread_cpu_seconds(pid)
    try:  # (absent from checkouts before it)
        names = get_json(port, "/bench/threads")
    except OSError:
        names = {}
    try:
        compiled = get_json(port, "/bench/compiles")
    except OSError:
        compiled = None
    peak = peak_rss_mb(pid) if peak_from else None
    end_own, end_rtsp = sum(os.times()[:2]), get_json(port, "/bench/rtsp") if rtsp_url else None
    end_counts, end_rtsp_frames = list(counts), reader.frames if reader else 0
    stop.set()
    for task in tasks:
        task.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
    if reader:
        reader.stop()
    span = end_t - start_t
    frames = {k: (end_state["frames"][k] - start_state["frames"][k]) / span
              for k in ("captured", "reconstructed", "encoded")}
    first_minute = [m for t, m in rss if t <= 60] or [rss[0][1]]
    out = {
        "fps_mean": {k: round(v, 2) for k, v in frames.items()},
        "fps_per_client_mean": round(float(np.mean([b - a for a, b in zip(start_counts, end_counts)])) / span, 2)
        if n_clients else None,
        "latency_client_ms": percentiles(latencies),
        "latency_server_ms": end_state["latency_ms"],
        "drops": end_state["drops"],
        "live_quality": end_state.get("live_quality"),
        "refresh": end_state.get("refresh"),
        "compiled_in_server": compiled,
        "cpu_percent": round(100 * (end_cpu - start_cpu) / span, 1),
        "clients_cpu_percent": round(100 * (end_own - start_own) / span, 1),
        "cpu_ms_per_frame": cpu_by_role(start_threads, end_threads, names,
                                        end_state["frames"]["reconstructed"] - start_state["frames"]["reconstructed"]),
        "rss_mb": {"after_first_minute": first_minute[-1], "end": rss[-1][1],
                   "growth_percent": round(100 * (rss[-1][1] - first_minute[-1]) / first_minute[-1], 2),
                   "samples": rss, "peak": peak, "peak_before": before},
    }
    if reader:
        out["rtsp"] = {"fps_server": round((end_rtsp["frames_encoded"] - start_rtsp["frames_encoded"]) / span, 2),
                       "fps_client": round((end_rtsp_frames - start_rtsp_frames) / span, 2),
                       "latency_client_ms": percentiles(reader.latencies), "error": reader.error,
                       "bitrate_kbps": end_rtsp["bitrate_kbps"], "arrival_to_push": end_rtsp["arrival_to_push"],
                       "width": end_rtsp["width"], "height": end_rtsp["height"]}
    return out


def h264_cost(size: tuple[int, int], fps: float, cfa: str, n: int = 120, threads: int = 0,
              preset: str = "ultrafast") -> dict:
    """The RTSP publisher's own cost, apart from the service: ``n`` previews of reconstructed, tone-mapped demo
    frames converted to I420 and pushed one at a time through the publisher's media (appsrc ! x264enc !
    rtph264pay, to a fakesink); CPU time of this process per frame (all its threads; nothing else runs in it meanwhile) and the wall
    time from push to the payloaded frame. CPU time, unlike wall time, hardly depends on the machine's load."""
    from service.publishers.rtsp import H264Settings, gstreamer, launch_description, to_i420
    from svelive.reconstruction.stream import Reconstructor
    from svelive.tonemap import ToneMapper, ToneSettings

    Gst = gstreamer()[0]
    demo = replay_source_factory(fps, size[0], size[1], n=8, cfa=cfa)()
    demo.open()
    previews = []
    mapper = ToneMapper(ToneSettings())
    with Reconstructor(demo.camera, temporal=False) as reconstructor:
        while len(previews) < 8:
            frame = demo.read(timeout=5.0)
            image = reconstructor.process(frame.raw).image
            previews.append(mapper(image, frame.host_time_ns) if image.ndim == 2 else
                            mapper(image, frame.host_time_ns, np.eye(3, dtype=np.float32), bgr=True))
    demo.close()
    height, width = previews[0].shape[:2]
    settings = H264Settings(fps=fps, threads=threads, speed_preset=preset)
    text = launch_description(width, height, settings)[1:-1]
    pipeline = Gst.parse_launch(text.strip() + " ! fakesink sync=false")
    done = threading.Semaphore(0)
    sizes: list[int] = []

    def encoded(pad, info):
        sizes.append(info.get_buffer().get_size())
        done.release()
        return Gst.PadProbeReturn.OK

    pipeline.get_by_name("enc").get_static_pad("src").add_probe(Gst.PadProbeType.BUFFER, encoded)
    src = pipeline.get_by_name("src")
    pipeline.set_state(Gst.State.PLAYING)
    walls, cpu0 = [], sum(os.times()[:2])
    for i in range(n):
        start = time.monotonic()
        src.emit("push-buffer", Gst.Buffer.new_wrapped(to_i420(previews[i % len(previews)]).tobytes()))
        if not done.acquire(timeout=10):
            raise SystemExit("x264enc produced nothing in 10 s")
        walls.append((time.monotonic() - start) * 1e3)
        time.sleep(max(0.0, 1 / fps - (time.monotonic() - start)))
    cpu = sum(os.times()[:2]) - cpu0
    pipeline.set_state(Gst.State.NULL)
    return {"size": f"{width}x{height}", "kind": "grey" if previews[0].ndim == 2 else "BGR",
            "cpu_ms_per_frame": round(cpu / n * 1e3, 1), "cpu_percent_at_fps": round(cpu / n * fps * 100, 1),
            "push_to_encoded_ms": percentiles(walls),
            "kbit_per_s_at_fps": round(float(np.mean(sizes)) * 8 * fps / 1000, 1),
            "bitrate_kbps_target": settings.bitrate_for(width, height)}


def report(name: str, load: dict) -> None:
    """Print one phase's figures."""
    print(f"{name}: fps captured {load['fps_mean']['captured']}, reconstructed {load['fps_mean']['reconstructed']}, "
          f"JPEG-encoded {load['fps_mean']['encoded']}, per MJPEG client {load['fps_per_client_mean']}; "
          f"server CPU {load['cpu_percent']} %, clients (this process) CPU {load['clients_cpu_percent']} %")
    if load["latency_client_ms"]["n"]:
        print(f"  MJPEG latency arrival -> part received by a client: p50 {load['latency_client_ms']['p50']} ms, "
              f"p95 {load['latency_client_ms']['p95']} ms (n={load['latency_client_ms']['n']})")
    if "rtsp" in load:
        r = load["rtsp"]
        print(f"  RTSP {r['width']}x{r['height']}: H.264-encoded {r['fps_server']} fps, decoded by the client "
              f"{r['fps_client']} fps, {r['bitrate_kbps']} kbit/s; latency arrival -> decoded: p50 "
              f"{r['latency_client_ms']['p50']} ms, p95 {r['latency_client_ms']['p95']} ms "
              f"(n={r['latency_client_ms']['n']}); arrival -> appsrc {json.dumps(r['arrival_to_push'])}"
              f"{'; client error: ' + r['error'] if r['error'] else ''}")
    print(f"  server CPU ms a reconstructed frame, by thread: {json.dumps(load['cpu_ms_per_frame'])}")
    print(f"  server stages: {json.dumps(load['latency_server_ms'])}")
    print(f"  drops: {json.dumps(load['drops'])}")
    if load.get("refresh"):
        print(f"  refresh at the end: {json.dumps(load['refresh'])}")
    live = load.get("live_quality")
    if live:
        print(f"  live quality ({live['mode']}) at the end: step {live['step']} {live['name']}, {live['changes']} "
              f"changes; {live['reason']}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--clients", type=int, default=10)
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--idle-s", type=float, default=15.0)
    parser.add_argument("--method", default=None)
    parser.add_argument("--no-temporal", action="store_true", help="single-frame reconstruction (no fusion)")
    parser.add_argument("--workers", type=int, default=0, help="reconstruction threads (0: one per core)")
    parser.add_argument("--parallel-frames", type=int, default=1, help="frames reconstructed at once (default 1)")
    parser.add_argument("--live-quality", choices=("fixed", "adaptive"), default="fixed",
                        help="fixed (default): the configured method and fusion throughout, as the targets are "
                             "stated; adaptive: the service's ladder steps down while it falls behind")
    parser.add_argument("--scene", choices=("pan", "static"), default="pan",
                        help="pan: the whole view moves every frame; static: a still view (default pan)")
    parser.add_argument("--size", default="1920x1200", help="frame size WxH (default 1920x1200)")
    parser.add_argument("--cfa", default="none",
                        help="none: the monochrome demo frames (default); RGGB (or another layout): the colour demo")
    parser.add_argument("--rtsp", action="store_true",
                        help="also serve RTSP/H.264 and measure MJPEG alone, MJPEG + 1 RTSP client, RTSP alone")
    parser.add_argument("--h264-cost", action="store_true",
                        help="only measure the RTSP encoder's CPU per frame on tone-mapped demo previews (no service)")
    parser.add_argument("--x264-threads", type=int, default=0, help="x264 threads (default 0: x264 chooses)")
    parser.add_argument("--x264-preset", default="ultrafast", help="x264 speed preset (default ultrafast)")
    parser.add_argument("--replay", choices=("fed", "held"), default="fed",
                        help="fed (default): the frames come from a feeder process through a pipe, a new buffer each, "
                             "as from a camera's driver; held: the server process holds the 24 rendered frames "
                             "(about 110 MB at 1920x1200, counted in its resident memory; the figures before "
                             "2026-11-29)")
    parser.add_argument("--refresh", type=int, default=None, metavar="K",
                        help="the service's refresh setting (monochrome streams with fusion run the method on the "
                             "bands that need it and 1/K of the settled ones; 0: off); default: the checkout's")
    parser.add_argument("--publisher-nice", type=int, default=None, metavar="N",
                        help="nice levels the publishers' threads run below the reconstruction (0: the same); "
                             "default: the checkout's")
    parser.add_argument("--publisher-idle", choices=("on", "off"), default=None,
                        help="on: the preview encoder's thread runs under SCHED_IDLE, only on a core the "
                             "reconstruction leaves idle (PipelineConfig.publisher_idle); off: its nice level alone; "
                             "default: the checkout's")
    parser.add_argument("--serve-port", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--feed", type=int, default=0, help=argparse.SUPPRESS)
    parser.add_argument("--rtsp-port", type=int, default=0, help=argparse.SUPPRESS)
    args = parser.parse_args()
    size = tuple(int(v) for v in args.size.lower().split("x"))
    if args.feed:
        feed(args.fps, size[0], size[1], args.feed, args.scene == "static", args.cfa)
        return
    if args.h264_cost:
        print(f"# load average {' '.join(open('/proc/loadavg').read().split()[:3])}, {os.cpu_count()} cores")
        print(json.dumps(h264_cost(size, args.fps, args.cfa, threads=args.x264_threads, preset=args.x264_preset)))
        return
    if args.serve_port:
        serve(args.serve_port, args.fps, args.method, not args.no_temporal, args.workers, args.scene == "static", size,
              args.cfa, args.rtsp_port, args.parallel_frames, args.live_quality, args.replay == "fed", args.refresh,
              args.publisher_nice, None if args.publisher_idle is None else args.publisher_idle == "on")
        return
    port = free_port()
    cmd = [sys.executable, __file__, "--serve-port", str(port), "--fps", str(args.fps), "--workers", str(args.workers),
           "--parallel-frames", str(args.parallel_frames), "--scene", args.scene, "--size", args.size, "--cfa", args.cfa,
           "--live-quality", args.live_quality, "--replay", args.replay]
    if args.method:
        cmd += ["--method", args.method]
    if args.no_temporal:
        cmd.append("--no-temporal")
    if args.refresh is not None:
        cmd += ["--refresh", str(args.refresh)]
    if args.publisher_nice is not None:
        cmd += ["--publisher-nice", str(args.publisher_nice)]
    if args.publisher_idle is not None:
        cmd += ["--publisher-idle", args.publisher_idle]
    rtsp_port = free_port() if args.rtsp else 0
    if rtsp_port:
        cmd += ["--rtsp-port", str(rtsp_port)]
    load_before = " ".join(open("/proc/loadavg").read().split()[:3])
    child = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "ready"
        deadline = time.monotonic() + 60
        while True:
            try:
                state = get_state(port)
                if state["frames"]["reconstructed"] > 10:
                    break
                if state.get("warming_up"):  # minutes where the kernels compile: the minute counts from the end
                    deadline = time.monotonic() + 60
            except OSError:
                pass
            if time.monotonic() > deadline:
                raise SystemExit("the service did not start")
            time.sleep(0.5)
        time.sleep(2)
        c0, s0 = cpu_seconds(child.pid), get_state(port)
        time.sleep(args.idle_s)
        c1, s1 = cpu_seconds(child.pid), get_state(port)
        idle = {"cpu_percent": round(100 * (c1 - c0) / args.idle_s, 1),
                "fps": s1["fps"], "encoded_frames": s1["frames"]["encoded"] - s0["frames"]["encoded"],
                "h264_frames": get_json(port, "/bench/rtsp")["frames_encoded"] if rtsp_port else None}
        loads = {f"{args.clients} MJPEG clients": asyncio.run(load_phase(port, child.pid, args.clients,
                                                                           args.minutes * 60))}
        if rtsp_port:
            url = f"rtsp://127.0.0.1:{rtsp_port}/live"
            loads[f"{args.clients} MJPEG clients + 1 RTSP client"] = asyncio.run(
                load_phase(port, child.pid, args.clients, args.minutes * 60, url))
            loads["1 RTSP client alone"] = asyncio.run(load_phase(port, child.pid, 0, args.minutes * 60, url))
    finally:
        child.terminate()
        child.wait(15)
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, load average before the run "
          f"{load_before}; {args.size} 12-bit "
          f"{'monochrome' if args.cfa == 'none' else args.cfa + ' colour'} replay at "
          f"{args.fps:g} fps, method {args.method or 'default'}{' single-frame' if args.no_temporal else ' + temporal'}, workers {args.workers or os.cpu_count()}, parallel frames {args.parallel_frames}, {args.scene} scene, "
          f"live quality {args.live_quality}, replay {args.replay}, {args.clients} clients, {args.minutes:g} min per phase"
          f"{'' if args.publisher_nice is None else f', publishers {args.publisher_nice} nice levels lower'}"
          f"{'' if args.publisher_idle is None else f', encoder SCHED_IDLE {args.publisher_idle}'}")
    print(f"no client: server CPU {idle['cpu_percent']} % of one core, {idle['encoded_frames']} frames JPEG-encoded"
          f"{'' if idle['h264_frames'] is None else ', ' + str(idle['h264_frames']) + ' H.264-encoded'}, "
          f"fps {idle['fps']}")
    for name, load in loads.items():
        report(name, load)
    load = loads[f"{args.clients} MJPEG clients"]
    print("RSS samples (s, MB): " + ", ".join(f"{t:.0f}: {m}" for t, m in load["rss_mb"]["samples"][5::6]))
    print(f"RSS after first minute {load['rss_mb']['after_first_minute']} MB, at end {load['rss_mb']['end']} MB, "
          f"growth {load['rss_mb']['growth_percent']} %; peak over the measured phase (VmHWM) "
          f"{load['rss_mb']['peak']} MB, before it (start-up, first frames, idle phase) "
          f"{load['rss_mb']['peak_before']} MB")
    if load.get("compiled_in_server") is not None:
        print(f"kernels the server compiled (not loaded from numba's cache) by the phase's end: "
              f"{len(load['compiled_in_server'])} {sorted(set(load['compiled_in_server']))}")
    if rtsp_port:
        base, both = loads[f"{args.clients} MJPEG clients"], loads[f"{args.clients} MJPEG clients + 1 RTSP client"]
        print(f"with / without RTSP (same run): server CPU {both['cpu_percent'] / base['cpu_percent']:.2f}, "
              f"reconstructed fps {both['fps_mean']['reconstructed'] / base['fps_mean']['reconstructed']:.2f}, "
              f"MJPEG p95 {both['latency_client_ms']['p95'] / base['latency_client_ms']['p95']:.2f}")


if __name__ == "__main__":
    main()
