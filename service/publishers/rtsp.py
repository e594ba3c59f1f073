"""RTSP/H.264 publisher: the tone-mapped preview for media servers, recorders and players.

GStreamer's RTSP server (``gst-rtsp-server`` through PyGObject): one :class:`RtspServer`
(one port) for every camera of the service, an :class:`RtspPublisher` per camera
mounted at its paths (``/cam/NAME``, the first camera also ``/live``), each one
shared media:

    preview_port ──PreviewFrame──> pusher thread: I420 (OpenCV/numpy) ─> appsrc (holds 1 frame, drops the older)
                                     ─> x264enc (zerolatency, no B-frames, 1 s GOP) ─> rtph264pay ─> clients

- Encoded once for every client: the media is shared (``set_shared(True)``), whichever
  of the camera's paths or ``?token=`` query a client uses (one media key per factory).
- Encoded only while a client is connected: the media is built when the first
  client asks for it and torn down after the last one leaves; only between the
  two does the publisher ask the pipeline for previews (``watch_previews``), which its
  pusher thread takes, the newest each time, from the pipeline's ``preview_port``,
  so with no client nothing is tone-mapped for RTSP and nothing is H.264-encoded
  (``frames_pushed`` and ``frames_encoded`` in :meth:`RtspPublisher.state` prove it).
- Grey and colour previews alike become I420 (BT.601, limited range) in the
  publisher: grey through a look-up table and neutral chroma, BGR through
  OpenCV (2-7 ms per 1920x1200 frame, against 10-14 ms in GStreamer's videoconvert).
- The pusher thread and the media's streaming thread (and with it x264's own threads) run
  ``publisher_nice`` levels below the reconstruction (service.pipeline.priority).
- Every client's first picture is a keyframe with its SPS/PPS: a client that starts playing is
  held (its transports inactive) until a keyframe reaches the payloader, and a key unit is
  forced for it (without x264's separate header buffer, which went out as a picture of its
  own), so a late joiner of the shared media neither gets the GOP's remaining delta frames
  first nor waits for the next periodic keyframe (frames are held back while its PLAY is
  answered, and the server's TCP sink is drained before it is let in: :func:`drain`).
  Forced keyframes are at least ``keyframe_gap_s`` (0.5 s) after the one before, so a
  reconnect storm cannot make every frame a keyframe: the clients that come meanwhile take
  the next one together.
- Time stamps: the running time rounded down to the nominal frame interval, a frame
  skipped when it falls in the slot of the one before (:func:`next_pts`), so they
  strictly increase and clients that count in frames never see two at one time.
- Never a queue: the appsrc holds one frame and drops the older one when the
  encoder is still busy; x264's zerolatency tune has no look-ahead and no
  frame threads; the payloader sends each frame as soon as it is encoded.
- Token: with a token every request needs it, as the password of RTSP basic
  authentication (any user name: ``rtsp://svelive:TOKEN@host:8554/live``) or as
  ``?token=TOKEN`` in the URL; a missing or wrong one gets ``401 Unauthorized``
  with a basic challenge, so clients that hold credentials in the URL retry with them.
- At most ``max_clients`` connections (64): beyond it the oldest connection that is not
  playing is closed (one that only holds a socket cannot lock out a recorder), or the new
  one when all the others play; checked at each accepted connection and, every CAP_SWEEP_S, against
  the server's own list of clients (an entry whose ``closed`` never came is dropped).
- The GLib main loop of the server runs in a thread of its own (its own main context).
- ``clients`` in the state counts the clients playing the stream (counted at PLAY, by path).

Debian packages: gir1.2-gst-rtsp-server-1.0 gir1.2-gst-plugins-base-1.0 gstreamer1.0-plugins-base
gstreamer1.0-plugins-good gstreamer1.0-plugins-ugly (x264enc); clients in the tests: gstreamer1.0-plugins-good
(rtspsrc) and gstreamer1.0-libav (avdec_h264).
"""

from __future__ import annotations

import base64
import binascii
import collections
import hmac
import socket
import threading
import time
import urllib.parse
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from service.pipeline import LatencyWindow, Pipeline, PreviewFrame, RateMeter
from service.pipeline.priority import lower_publisher
from svelive.core.errors import SveliveError

#: What to install when the GStreamer RTSP server or its plugins are missing.
SETUP_HINT = ("apt-get install gir1.2-gst-rtsp-server-1.0 gir1.2-gst-plugins-base-1.0 gstreamer1.0-plugins-good "
              "gstreamer1.0-plugins-ugly")
#: The elements the media needs (x264enc is in gstreamer1.0-plugins-ugly).
ELEMENTS = ("appsrc", "x264enc", "rtph264pay")
#: Bits per pixel per frame of the default H.264 rate: about 4.8 Mbit/s at 1920x1200 and 30 fps.
BITS_PER_PIXEL = 0.07
#: The media factory role a valid token gives (its permissions are set in ``RtspServer.start``).
ROLE = "viewer"
#: Connections the RTSP port keeps at once (players and connections still negotiating).
MAX_CLIENTS = 64
#: How often (s) the server recounts its clients against MAX_CLIENTS, besides at each accepted connection.
CAP_SWEEP_S = 0.25
#: Connections waiting to be accepted (GStreamer's default, 5, made a burst of clients wait 1-3 s in SYN retries).
BACKLOG = 128
#: The longest a PLAY waits for the frame going through the payloader to be taken from the server's sinks (s).
PAUSE_WAIT_S = 0.2
#: Timecode: bits of the capture time in ms, and the side of one bit's square in pixels.
TIMECODE_BITS = 48
TIMECODE_BLOCK = 8


def gstreamer() -> tuple[Any, Any, Any, Any]:
    """The GStreamer modules ``(Gst, GstRtspServer, GstRtsp, GLib)``, initialised.

    Raises a one-line SveliveError naming the packages when the typelibs or an element are missing.
    """
    try:
        import gi

        gi.require_version("Gst", "1.0")
        gi.require_version("GstRtspServer", "1.0")
        gi.require_version("GstRtsp", "1.0")
        gi.require_version("GstVideo", "1.0")
        from gi.repository import GLib, Gst, GstRtsp, GstRtspServer, GstVideo  # noqa: F401 - GstVideo: keyframes
    except (ImportError, ValueError) as exc:
        raise SveliveError(f"RTSP needs PyGObject and GStreamer's RTSP server ({exc}); install: {SETUP_HINT}") \
            from None
    if not Gst.is_initialized():
        Gst.init(None)
    missing = [name for name in ELEMENTS if Gst.ElementFactory.find(name) is None]
    if missing:
        raise SveliveError(f"RTSP needs the GStreamer element(s) {', '.join(missing)}; install: {SETUP_HINT}")
    return Gst, GstRtspServer, GstRtsp, GLib


@dataclass(frozen=True)
class H264Settings:
    """The encoder's settings.

    Attributes:
        fps: the nominal frame rate (caps, keyframe interval and bitrate; the timestamps are the real ones).
        keyframe_s: seconds between keyframes at the nominal rate (and one whenever a client starts playing).
        bitrate_kbps: H.264 rate in kbit/s; 0: from the frame size (``BITS_PER_PIXEL``).
        speed_preset: x264's speed preset (``ultrafast``, ``superfast``, ``veryfast``...).
        threads: x264 threads (0: x264 chooses; with zerolatency they are slice threads, no added latency).
    """

    fps: float = 30.0
    keyframe_s: float = 1.0
    bitrate_kbps: int = 0
    speed_preset: str = "ultrafast"
    threads: int = 0

    def __post_init__(self) -> None:
        if not 0 < self.fps <= 240:
            raise SveliveError(f"RTSP fps must be in (0, 240], got {self.fps}")
        if not 0 < self.keyframe_s <= 60:
            raise SveliveError(f"RTSP keyframe interval must be in (0, 60] s, got {self.keyframe_s}")
        if not 0 <= self.bitrate_kbps <= 100_000:
            raise SveliveError(f"RTSP bitrate must be 0 (from the size) to 100000 kbit/s, got {self.bitrate_kbps}")
        if self.speed_preset not in ("ultrafast", "superfast", "veryfast", "faster", "fast", "medium"):
            raise SveliveError(f"unknown x264 speed preset {self.speed_preset!r}; use ultrafast or superfast")

    def bitrate_for(self, width: int, height: int) -> int:
        """kbit/s for frames of ``width`` x ``height`` pixels: the configured rate, or one from the size."""
        return self.bitrate_kbps or bitrate_kbps(width, height, self.fps)


def bitrate_kbps(width: int, height: int, fps: float, bits_per_pixel: float = BITS_PER_PIXEL) -> int:
    """An H.264 rate in kbit/s for a live preview: ``bits_per_pixel`` per pixel per frame, at least 200."""
    return max(200, int(round(width * height * fps * bits_per_pixel / 1000)))


def launch_description(width: int, height: int, settings: H264Settings) -> str:
    """The gst-launch description of the shared media for I420 frames of this size (both even).

    appsrc: live, timestamped at push, one frame held, the older dropped (never a
    queue); x264: zerolatency (no look-ahead, no frame threads), no B-frames, a
    keyframe every ``keyframe_s``, constrained baseline (every decoder, browsers
    included), as an Annex B byte stream, in which x264 puts SPS and PPS at the head of every
    keyframe (a client can join at any one). The payloader adds none of its own
    (``config-interval=0``): with ``-1`` it put them before every slice of a keyframe (x264 cuts a
    frame into one slice per thread), so a client saw one picture per slice, each with the others
    missing (the lower part a smear) and two pictures with one time stamp.
    """
    fps = max(1, int(round(settings.fps)))
    caps = f"video/x-raw,format=I420,width={width},height={height},framerate={fps}/1,colorimetry=bt601"
    gop = max(1, int(round(settings.fps * settings.keyframe_s)))
    return (f"( appsrc name=src is-live=true do-timestamp=true format=time block=false max-buffers=1 "
            f"leaky-type=downstream caps=\"{caps}\" "
            f"! x264enc name=enc tune=zerolatency speed-preset={settings.speed_preset} "
            f"bitrate={settings.bitrate_for(width, height)} key-int-max={gop} bframes=0 threads={settings.threads} "
            f"! video/x-h264,profile=constrained-baseline,stream-format=byte-stream,alignment=au "
            f"! rtph264pay name=pay0 pt=96 config-interval=0 aggregate-mode=zero-latency )")


def running_time_ns(now_ns: int, base_time_ns: int) -> int:
    """The running time (ns) to stamp on a frame pushed at clock time ``now_ns`` into an element whose
    base time is ``base_time_ns``: ``now - base``, or 0 while the base time is not set yet (0) or ahead.

    appsrc's own ``do-timestamp`` computes ``now - base`` at push time, and a push in the short window of
    the PAUSED -> PLAYING change where the element already has the pipeline's clock but not yet its base
    time gave the frame the absolute clock time (the machine's uptime) as running time: the RTSP stream's
    synchronised sink then held it, and every frame after it, until that time (seen as a client stuck
    paused after PLAY with one frame encoded). In that window the running time is about 0.
    """
    return now_ns - base_time_ns if 0 < base_time_ns <= now_ns else 0


def next_pts(running_ns: int, last_pts_ns: int | None, interval_ns: int) -> int | None:
    """The time stamp (ns) of a frame whose running time is ``running_ns``, after a frame stamped ``last_pts_ns``
    (None: the media's first), or None to skip the frame: the running time rounded down to a whole number of
    ``interval_ns`` (one frame at the nominal rate); where that slot is taken, the next one, if it is at most half
    an interval ahead of the running time; else the frame is skipped.

    Why: a frame pushed before the pipeline plays and the first one pushed as it starts both have a running
    time of about 0 (:func:`running_time_ns`), and two pictures with one RTP time stamp are one picture to a
    client; and clients that count time in frames (ffmpeg counts in frames of the rate it guesses from the
    time stamps' spacing) gave two frames closer than that one number ("non monotonically increasing dts").
    On the grid of the nominal interval every frame has a slot of its own and the guessed rate is the
    nominal one. Frames at the nominal rate with jitter often fall twice into one slot: the later one takes the
    next slot (a stamp at most half an interval ahead of the running time), so no picture is lost to jitter;
    only a frame less than half an interval after the one before is skipped (counted by the caller)."""
    slot = running_ns // interval_ns * interval_ns
    if last_pts_ns is None or slot > last_pts_ns:
        return slot
    following = last_pts_ns + interval_ns
    return following if following - running_ns <= interval_ns // 2 else None


def media_running_time(src: Any) -> int:
    """The running time (ns) of the appsrc ``src`` now: :func:`running_time_ns` of its clock and base time,
    0 before the pipeline has a clock."""
    clock = src.get_clock()
    return 0 if clock is None else running_time_ns(clock.get_time(), src.get_base_time())


def push_frame(src: Any, data: bytes, pts_ns: int | None = None) -> None:
    """Push one raw frame into the appsrc ``src`` stamped with ``pts_ns`` (default: its running time now,
    :func:`media_running_time`)."""
    from gi.repository import Gst

    buffer = Gst.Buffer.new_wrapped(data)
    buffer.pts = buffer.dts = media_running_time(src) if pts_ns is None else pts_ns
    src.emit("push-buffer", buffer)


def server_sinks(pipeline: Any) -> list[Any]:
    """The RTSP server's sinks in a media's ``pipeline`` (appsink for RTP over TCP, multiudpsink over UDP), made to
    send each packet at once, not at its time stamp.

    Why unsynchronised: a frame stamped up to half an interval ahead (:func:`next_pts`) waited in the sink while the
    keyframe after it let a waiting client in (``RtspPublisher._on_payload``), which then got that delta frame
    first. The frames are live, stamped at about the running time of their push: there is nothing to pace. The
    server makes its sinks with the first transport of their kind, so this is asked again at every PLAY."""
    from gi.repository import Gst

    sinks = []
    elements = pipeline.iterate_recurse()
    while True:
        result, element = elements.next()
        if result != Gst.IteratorResult.OK:
            return sinks
        factory = element.get_factory()
        if factory is not None and factory.get_name() in ("appsink", "multiudpsink"):
            if element.get_property("sync"):
                element.set_property("sync", False)
            sinks.append(element)


def drain(sinks: list[Any]) -> None:
    """Wait until the server has taken every packet out of its appsinks (a drain query: an appsink answers it
    when its queue is empty). Over TCP the server's sending thread takes a packet from the appsink and hands it to
    the transports active at that moment, and it takes it only when one of them can take more, so a packet made
    before a client is let in could otherwise go to it after. UDP sinks send as they receive."""
    from gi.repository import Gst

    for sink in sinks:
        if sink.get_factory().get_name() == "appsink":
            sink.get_static_pad("sink").query(Gst.Query.new_drain())


def even_size(image: np.ndarray) -> np.ndarray:
    """``image`` cropped to an even width and height (4:2:0 H.264 needs both), a view."""
    return image[:image.shape[0] // 2 * 2, :image.shape[1] // 2 * 2]


def studio_swing_table() -> np.ndarray:
    """The uint8 (256,) look-up table from full-range grey to BT.601 limited-range luma (16..235)."""
    return np.round(16 + np.arange(256) * (219 / 255)).astype(np.uint8)


def to_i420(image: np.ndarray) -> np.ndarray:
    """I420 (BT.601, limited range) of a uint8 grey (H, W) or BGR (H, W, 3) image with even H and W: uint8
    (3 H / 2, W), the Y plane then the U and V planes (H/2, W/2) each, row after row. Grey gets neutral chroma."""
    if image.ndim == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2YUV_I420)
    height = image.shape[0]
    out = np.empty((height * 3 // 2, image.shape[1]), np.uint8)
    out[:height] = cv2.LUT(image, studio_swing_table())
    out[height:] = 128
    return out


def stamp_timecode(image: np.ndarray, wall_ms: int) -> None:
    """Write ``wall_ms`` (Unix time in ms) into the top-left corner of uint8 ``image`` (H, W) or (H, W, C), in place:
    TIMECODE_BITS squares of TIMECODE_BLOCK pixels, white for 1 and black for 0, most significant first."""
    bits = [(wall_ms >> (TIMECODE_BITS - 1 - i)) & 1 for i in range(TIMECODE_BITS)]
    strip = np.repeat(np.repeat(np.array(bits, np.uint8)[None, :] * 255, TIMECODE_BLOCK, 0), TIMECODE_BLOCK, 1)
    image[:TIMECODE_BLOCK, :TIMECODE_BITS * TIMECODE_BLOCK] = strip if image.ndim == 2 else strip[..., None]


def read_timecode(image: np.ndarray) -> int:
    """The Unix time in ms written by :func:`stamp_timecode`, read back from a decoded uint8 ``image`` (the mean
    of the centre of each square, thresholded at mid-grey: it survives lossy coding)."""
    grey = image if image.ndim == 2 else image.mean(axis=2)
    inset = TIMECODE_BLOCK // 4
    squares = grey[inset:TIMECODE_BLOCK - inset, :TIMECODE_BITS * TIMECODE_BLOCK]
    squares = squares.reshape(squares.shape[0], TIMECODE_BITS, TIMECODE_BLOCK)[:, :, inset:TIMECODE_BLOCK - inset]
    value = 0
    for bit in squares.mean(axis=(0, 2)) > 127.5:
        value = (value << 1) | int(bit)
    return value


def token_matches(token: str, authorization: str | None, query: str | None) -> bool:
    """True if the request carries ``token``: as the password of ``Authorization: Basic`` (any user name) or as
    ``token=`` in the URL query. Compared in constant time."""
    candidates = []
    if authorization and authorization[:6].lower() == "basic ":
        try:
            candidates.append(base64.b64decode(authorization[6:].strip(), validate=True).decode().partition(":")[2])
        except (binascii.Error, UnicodeDecodeError):
            pass
    if query:
        candidates += urllib.parse.parse_qs(query).get("token", [])
    expected = token.encode()
    return any(hmac.compare_digest(candidate.encode(), expected) for candidate in candidates)


class _Media:
    """The live media's appsrc and encoder, and the frame size fixed for its lifetime."""

    def __init__(self, media: Any, src: Any, encoder: Any, width: int, height: int) -> None:
        self.media = media
        self.src = src
        self.encoder = encoder
        self.width = width
        self.height = height
        #: the time stamp of the last frame pushed (ns), None before the first (:func:`next_pts`)
        self.last_pts: int | None = None
        #: clients that started playing and their transports, made inactive until the next keyframe
        self.joining: dict[Any, list[Any]] = {}
        #: when the last keyframe reached the payloader (monotonic ns; 0: none yet)
        self.last_keyframe_ns = 0
        #: a client has started playing it (the first one gets the media's first frame, a keyframe, at PLAY)
        self.played = False
        #: the server's sinks (:func:`server_sinks`, found at each PLAY)
        self.sinks: list[Any] = []
        #: the payloader's sink pad; the probe that holds frames back there while a PLAY is answered (0: none),
        #: and since when (monotonic s)
        self.pay_sink: Any = None
        self.pause_id = 0
        self.paused_at = 0.0


def check_path(path: str) -> str:
    """``path`` if it names an RTSP mount point (``/live``, ``/cam/dock``); a one-line SveliveError otherwise."""
    if not path.startswith("/") or len(path) < 2 or any(c in path for c in "?# ") or path.endswith("/"):
        raise SveliveError(f"RTSP path must start with / and name a mount point (e.g. /live), got {path!r}")
    return path


def port_error(host: str, port: int) -> SveliveError:
    return SveliveError(f"cannot listen for RTSP on {host}:{port} (in use or not allowed); choose another --rtsp port")


def check_port(host: str, port: int) -> None:
    """A one-line SveliveError when ``host:port`` cannot be bound now (checked before a long start-up; the
    server binds it later)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind((host, port))
            probe.listen(1)
        except OSError:
            raise port_error(host, port) from None


def _close(client: Any) -> None:
    """Close ``client`` from the server's thread: its socket is shut down, so that the thread serving the client
    reads the end and closes it there. ``gst_rtsp_client_close`` from another thread than the client's races with
    its read (GLib-GIO-CRITICAL "g_pollable_input_stream_read_nonblocking: assertion failed") and under load left
    the connection open: 128 of 300 held connections against a cap of 64. The client's own close is the fallback
    when it has no socket yet."""
    connection = client.get_connection()
    socket = connection.get_read_socket() if connection is not None else None
    if socket is None:
        client.close()
        return
    try:
        socket.shutdown(True, True)
    except Exception:  # already shut (GLib.Error): the client is closing anyway
        pass


class RtspServer:
    """One RTSP server: one port, one GLib main loop (a thread of its own), one token, and a mount
    point per stream (:class:`RtspPublisher`), so that every camera of a service is on one port
    (``rtsp://HOST:PORT/cam/NAME``), as media servers (MediaMTX, go2rtc) serve their paths.

    ``add`` the publishers, then ``start()`` binds ``host:port`` (port 0: a free one); ``stop()``
    closes every client and ends the loop (within a second).
    """

    def __init__(self, *, host: str = "127.0.0.1", port: int = 8554, token: str | None = None,
                 max_clients: int = MAX_CLIENTS) -> None:
        if not 0 <= port <= 65535:
            raise SveliveError(f"RTSP port must be 0..65535, got {port}")
        if max_clients < 1:
            raise SveliveError(f"RTSP client limit must be at least 1, got {max_clients}")
        self.host = host
        self.port = port
        self.token = token
        self.max_clients = max_clients
        self.publishers: list[RtspPublisher] = []
        #: connected clients, oldest first: added on the server's GLib thread, removed by their ``closed`` signal,
        #: which comes on the thread that drops the client's watch (often gst-rtsp-server's client thread): locked
        self._clients: dict[Any, None] = {}
        self._clients_lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._loop: Any = None
        self._context: Any = None
        self._server: Any = None
        self._source_id = 0
        self._sweep_source: Any = None

    def add(self, publisher: RtspPublisher) -> None:
        """Serve ``publisher`` at its paths (before ``start``); a path already served is a SveliveError."""
        if self._thread is not None:
            raise SveliveError("add RTSP streams before the server starts")
        taken = {path for other in self.publishers for path in other.paths}
        clash = sorted(taken & set(publisher.paths))
        if clash:
            raise SveliveError(f"RTSP path {clash[0]} is served twice: give every camera its own name")
        self.publishers.append(publisher)

    def url(self, path: str) -> str:
        """The URL of ``path`` (the bound port once started; 127.0.0.1 when bound to every address)."""
        shown = "127.0.0.1" if self.host in ("0.0.0.0", "::", "") else self.host
        shown = f"[{shown}]" if ":" in shown else shown
        return f"rtsp://{shown}:{self.port}{path}"

    def start(self) -> RtspServer:
        """Bind and serve; returns self. A busy port or missing GStreamer parts are a one-line SveliveError."""
        if self._thread is not None:
            return self
        Gst, GstRtspServer, GstRtsp, GLib = gstreamer()
        server = GstRtspServer.RTSPServer()
        server.set_address(self.host)
        server.set_service(str(self.port))
        server.set_backlog(BACKLOG)
        role = None
        if self.token is not None:
            role = GstRtspServer.RTSPToken()
            role.set_string("media.factory.role", ROLE)
            server.set_auth(_make_auth(GstRtspServer, GstRtsp, self.token, role))
        mounts = server.get_mount_points()
        for publisher in self.publishers:
            factory = publisher.factory(Gst, GstRtspServer)
            if role is not None:
                factory.add_role_from_structure(Gst.Structure.new_from_string(
                    f"{ROLE}, media.factory.access=(boolean)true, media.factory.construct=(boolean)true"))
            for path in publisher.paths:  # one factory at every path: one shared media, one encoding
                mounts.add_factory(path, factory)
        server.connect("client-connected", self._on_client_connected)
        context = GLib.MainContext.new()
        source_id = server.attach(context)
        if not source_id:
            raise port_error(self.host, self.port)
        self.port = server.get_bound_port()
        self._server, self._context, self._source_id = server, context, source_id
        # the cap again, from the server's own list of clients, every CAP_SWEEP_S (see _sweep)
        sweep = GLib.timeout_source_new(int(CAP_SWEEP_S * 1000))
        sweep.set_callback(self._sweep)
        sweep.attach(context)
        self._sweep_source = sweep
        self._loop = GLib.MainLoop.new(context, False)
        for publisher in self.publishers:
            publisher.attach()
        self._thread = threading.Thread(target=self._loop.run, name="svelive-rtsp", daemon=True)
        self._thread.start()
        return self

    def stop(self, timeout: float = 1.0) -> None:
        """Disconnect every client, stop encoding and end the main loop (idempotent, within ``timeout`` s)."""
        if self._thread is None:
            return
        from gi.repository import GstRtspServer

        for publisher in self.publishers:
            publisher.detach()
        done = threading.Event()

        def shut_down() -> bool:
            self._server.client_filter(lambda server, client: GstRtspServer.RTSPFilterResult.REMOVE)
            source = self._context.find_source_by_id(self._source_id)
            if source is not None:
                source.destroy()
            if self._sweep_source is not None:
                self._sweep_source.destroy()
            self._loop.quit()
            done.set()
            return False

        self._context.invoke_full(0, shut_down)
        done.wait(timeout)
        self._thread.join(max(0.0, timeout - 0.1))
        for publisher in self.publishers:
            publisher.release()
        self._thread = None

    def __enter__(self) -> RtspServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def publisher_at(self, path: str) -> RtspPublisher | None:
        """The publisher serving ``path`` (a mount point, or a stream's control URL below one), or None."""
        for publisher in self.publishers:
            if any(path == p or path.startswith(p + "/") for p in publisher.paths):
                return publisher
        return None

    def _on_client_connected(self, server: Any, client: Any) -> None:
        """GLib thread, a connection accepted: beyond ``max_clients`` the oldest one that is not playing is
        closed to make room (a connection that holds a slot without playing cannot lock out a recorder), or,
        when every other one plays, the new one."""
        with self._clients_lock:
            self._clients[client] = None
        client.connect("closed", self._forget_client)
        victims = self._over_cap(newest=client)
        for victim in victims:
            _close(victim)
        if client in victims:
            return
        client.connect("pre-play-request", self._on_pre_play)
        client.connect("play-request", self._on_play)

    def _forget_client(self, client: Any) -> None:
        """Any thread, ``client`` closed."""
        with self._clients_lock:
            self._clients.pop(client, None)

    def _over_cap(self, newest: Any = None) -> list[Any]:
        """The clients to close to be within ``max_clients`` (taken out of the count): the oldest that are not
        playing, then ``newest`` (a connection being accepted), then the oldest of the others."""
        with self._clients_lock:
            excess = len(self._clients) - self.max_clients
            if excess <= 0:
                return []
            order = [c for c in self._clients if c is not newest]
            idle = [c for c in order if getattr(c, "svelive_publisher", None) is None]
            playing = [c for c in order if getattr(c, "svelive_publisher", None) is not None]
            ranked = idle + ([newest] if newest is not None else []) + playing
            victims = ranked[:excess]
            for victim in victims:
                self._clients.pop(victim, None)
        return victims

    def _sweep(self, *_: Any) -> bool:
        """GLib thread, every CAP_SWEEP_S: the count checked against the server's own list of its clients.
        Entries whose ``closed`` never came are dropped, and any excess is closed. Clients the server still lists
        but the count does not are not put back: they are the ones the cap closed, whose watch the server has not
        dropped yet (put back as the newest, they made the count of a burst of connections look hundreds over
        the cap, and the cap then closed every idle client, a player still negotiating among them)."""
        alive = set(self._server.client_filter(None) if self._server is not None else [])
        with self._clients_lock:
            for client in [c for c in self._clients if c not in alive]:
                del self._clients[client]
        for victim in self._over_cap():
            _close(victim)
        return True

    def _on_pre_play(self, client: Any, ctx: Any) -> Any:
        """GLib thread, a PLAY is about to be answered: hold frames back until it is (see
        :meth:`RtspPublisher.pause_payloads`)."""
        from gi.repository import GstRtsp

        publisher = self.publisher_at(ctx.uri.abspath if ctx.uri is not None else "")
        if publisher is not None:
            publisher.pause_payloads()
        return GstRtsp.RTSPStatusCode.OK

    def _on_play(self, client: Any, ctx: Any) -> None:
        """GLib thread, a client starts playing: it counts as a client of the stream it plays (once)."""
        publisher = self.publisher_at(ctx.uri.abspath if ctx.uri is not None else "")
        if publisher is None:
            return
        if getattr(client, "svelive_publisher", None) is None:
            client.svelive_publisher = publisher
            publisher.client_started()
            client.connect("closed", self._on_client_closed)
            client.connect("teardown-request", self._on_teardown)
        if ctx.sessmedia is not None:
            # get_transport(i), not get_transports(): PyGObject takes the array's elements as owned (transfer
            # full), which they are not, and the transports were freed under the client (an abort)
            transports = [ctx.sessmedia.get_transport(i) for i in range(ctx.sessmedia.get_media().n_streams())]
            publisher.hold_until_keyframe(client, [t for t in transports if t is not None])

    @staticmethod
    def _on_teardown(client: Any, ctx: Any) -> None:
        publisher = getattr(client, "svelive_publisher", None)
        if publisher is not None:
            publisher.forget_joiner(client)

    @staticmethod
    def _on_client_closed(client: Any) -> None:
        publisher = getattr(client, "svelive_publisher", None)
        if publisher is not None:
            client.svelive_publisher = None
            publisher.forget_joiner(client)
            publisher.client_ended()


class RtspPublisher:
    """Serves a pipeline's tone-mapped preview as H.264 over RTSP at ``paths`` of an :class:`RtspServer`.

    Without ``server``, it runs a server of its own (``host``, ``port``, ``token``), started and
    stopped with it; with one, the server starts and stops it. ``paths``: the mount points
    (the first is the one ``url`` names); all of them share one media, so one encoding.
    ``timecode``: write each frame's arrival time into its top-left corner (a measuring aid for
    benchmarks/service.py, see :func:`read_timecode`; off by default).
    """

    def __init__(self, pipeline: Pipeline, *, host: str = "127.0.0.1", port: int = 8554, path: str = "/live",
                 token: str | None = None, settings: H264Settings | None = None, timecode: bool = False,
                 server: RtspServer | None = None, aliases: tuple[str, ...] = ()) -> None:
        self.paths = tuple(check_path(p) for p in (path, *aliases))
        self.path = self.paths[0]
        self.pipeline = pipeline
        self.settings = settings or H264Settings()
        self.timecode = timecode
        self._own = server is None
        self.server = RtspServer(host=host, port=port, token=token) if server is None else server
        self.server.add(self)
        self._lock = threading.Lock()
        self._media: _Media | None = None
        self._watching = False
        self._keyframe_wanted = False  # a client waits for a keyframe: the pusher thread forces one
        #: the least time (s) from a keyframe to a forced one (clients joining meanwhile wait for the next)
        self.keyframe_gap_s = 0.5
        self.keyframes_forced = 0
        self.joins = 0  # clients let in at a keyframe
        self._clients = 0
        self.pushed = RateMeter()
        self.skipped = 0  # previews not pushed: less than half a nominal interval after the one before
        self.encoded = RateMeter()
        self._bytes: collections.deque[tuple[int, int]] = collections.deque(maxlen=512)
        self.arrival_to_push = LatencyWindow()
        #: medias made so far (one per period with clients: the media is shared)
        self.medias = 0
        #: how long a client arriving before the first reconstructed frame waits for it (blocks the RTSP loop)
        self.first_frame_wait_s = 3.0
        self._pusher: threading.Thread | None = None
        self._detached = threading.Event()

    # ----- lifecycle ---------------------------------------------------
    @property
    def url(self) -> str:
        """The stream's URL (its first path)."""
        return self.server.url(self.path)

    @property
    def port(self) -> int:
        return self.server.port

    @property
    def token(self) -> str | None:
        return self.server.token

    def start(self) -> RtspPublisher:
        """Start the publisher's own server (a shared server is started by its owner); returns self."""
        if self._own:
            self.server.start()
        return self

    def stop(self, timeout: float = 1.0) -> None:
        """Stop the publisher's own server (idempotent, within ``timeout`` s)."""
        if self._own:
            self.server.stop(timeout)

    def __enter__(self) -> RtspPublisher:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def factory(self, Gst: Any, GstRtspServer: Any) -> Any:
        """GLib objects: the shared-media factory of this stream (called by the server at start)."""
        factory = _make_factory(Gst, GstRtspServer, self._description)
        factory.set_shared(True)
        factory.connect("media-configure", self._on_media_configure)
        return factory

    def attach(self) -> None:
        """The server started (once): take previews from the pipeline's ``preview_port`` in a thread of our own
        (pushed only while a media exists)."""
        self._detached.clear()
        self._pusher = threading.Thread(target=self._push_previews, name="svelive-rtsp-push", daemon=True)
        self._pusher.start()

    def detach(self, timeout: float = 1.0) -> None:
        """The server stops (once, after ``attach``): no more previews."""
        self._detached.set()
        self.pipeline.preview_port.wake()
        if self._pusher is not None:
            self._pusher.join(timeout)
            self._pusher = None

    def _push_previews(self) -> None:
        """The pusher thread: each new preview of the pipeline's ``preview_port`` (the newest one; a preview made
        while the one before was still being pushed is skipped), until :meth:`detach`."""
        port = self.pipeline.preview_port
        seen = port.seq
        lower_publisher(self.pipeline.config.publisher_nice)
        while not self._detached.is_set():
            got = port.get_newest(seen, 0.25)
            if got is not None:
                seen, preview = got
                self._on_preview(preview)

    def release(self) -> None:
        """The server stopped: let the encoder stage stop making previews for us, drop the media."""
        with self._lock:
            media, self._media = self._media, None
            watching, self._watching = self._watching, False
            self._clients = 0
        if watching:
            self.pipeline.watch_previews(-1)
        if media is not None:
            media.media.unprepare()

    def client_started(self) -> None:
        with self._lock:
            self._clients += 1

    def client_ended(self) -> None:
        with self._lock:
            self._clients = max(0, self._clients - 1)

    # ----- the media -----------------------------------------------------
    def _description(self) -> str:
        """GLib thread, for each new media: the launch line for the newest preview's size (the newest
        reconstructed frame's before the first preview, waiting up to ``first_frame_wait_s`` for one; then
        640x360, the no-signal frame's)."""
        preview = self.pipeline.latest_preview()
        latest = self.pipeline.latest()
        if preview is None and latest is None:  # just started
            got = self.pipeline.hdr_port.get_newest(0, self.first_frame_wait_s)
            latest = None if got is None else got[1]
        if preview is not None:
            height, width = preview.image.shape[:2]
        elif latest is not None:
            height, width = latest.hdr.image.shape[:2]
        else:  # no frame yet: the no-signal frame's size
            width, height = 640, 360
        if preview is None:  # the size of a preview of that frame
            width, height = self.pipeline.preview_size(width, height)
        return launch_description(width // 2 * 2, height // 2 * 2, self.settings)

    def _on_media_configure(self, factory: Any, media: Any) -> None:
        """GLib thread: a new shared media (the first client): take its appsrc, count its encoded frames,
        ask the encoder for previews until it is unprepared (the last client left)."""
        from gi.repository import Gst

        element = media.get_element()
        src, encoder = element.get_by_name("src"), element.get_by_name("enc")
        caps = src.get_property("caps").get_structure(0)
        self.medias += 1
        encoder.get_static_pad("src").add_probe(Gst.PadProbeType.BUFFER, self._on_encoded)
        encoder.get_static_pad("sink").add_probe(Gst.PadProbeType.EVENT_DOWNSTREAM, self._on_stream_start)
        media.connect("unprepared", self._on_media_unprepared)
        record = _Media(media, src, encoder, caps.get_value("width"), caps.get_value("height"))
        record.pay_sink = element.get_by_name("pay0").get_static_pad("sink")
        record.pay_sink.add_probe(Gst.PadProbeType.BUFFER, self._on_payload, record)
        with self._lock:
            self._media = record
            start_watching = not self._watching
            self._watching = True
        if start_watching:
            self.pipeline.watch_previews(+1)
        # the media is prepared once its first frame has gone through: give it the newest frame's preview now
        # if it exists (the encoder makes a preview only of a newer frame); an older one waits for the next
        preview, latest = self.pipeline.latest_preview(), self.pipeline.latest()
        if preview is not None and latest is not None and preview.hdr_seq == latest.seq and self.pipeline.online():
            self._on_preview(preview)

    def _on_stream_start(self, pad: Any, info: Any) -> Any:
        """The media's streaming thread, at its first event: lower it below the reconstruction before x264 (at
        the caps that follow) starts the threads that inherit its priority (service.pipeline.priority)."""
        from gi.repository import Gst

        if info.get_event().type != Gst.EventType.STREAM_START:
            return Gst.PadProbeReturn.OK
        lower_publisher(self.pipeline.config.publisher_nice)
        return Gst.PadProbeReturn.REMOVE

    def _on_media_unprepared(self, media: Any) -> None:
        with self._lock:
            if self._media is None or self._media.media != media:
                return
            self._media = None
            stop_watching, self._watching = self._watching, False
        if stop_watching:
            self.pipeline.watch_previews(-1)

    def _on_encoded(self, pad: Any, info: Any) -> Any:
        from gi.repository import Gst

        buffer = info.get_buffer()
        now = time.monotonic_ns()
        self.encoded.tick(now)
        self._bytes.append((now, buffer.get_size()))
        return Gst.PadProbeReturn.OK

    def _on_payload(self, pad: Any, info: Any, record: _Media) -> Any:
        """Streaming thread, an encoded frame on its way to the payloader: at a keyframe, let the clients waiting
        for one in (their transports active again), so that it is the first picture they get."""
        from gi.repository import Gst

        if info.get_buffer().has_flags(Gst.BufferFlags.DELTA_UNIT):
            return Gst.PadProbeReturn.OK
        with self._lock:
            media = self._media
            if media is not record:  # a media on its way out
                return Gst.PadProbeReturn.OK
            sinks = list(media.sinks) if media.joining else []
        drain(sinks)  # the frame before it may still wait in the server's sink (taken for the clients let in now)
        with self._lock:
            if self._media is not record:
                return Gst.PadProbeReturn.OK
            media.last_keyframe_ns = time.monotonic_ns()
            joining, media.joining = media.joining, {}
            self._keyframe_wanted = False
            # under the lock: a client that closes (forget_joiner) is never let in after it went
            for transports in joining.values():
                for transport in transports:
                    transport.set_active(True)
            self.joins += len(joining)
        return Gst.PadProbeReturn.OK

    def pause_payloads(self) -> None:
        """GLib thread, before a PLAY of a media that plays already: stop frames at the payloader and wait
        (at most PAUSE_WAIT_S) until the one going through has been taken for the clients (:func:`drain`). Why: the
        server makes the new client's transports active before :meth:`hold_until_keyframe` can make them inactive
        again, and a frame sent meanwhile (the GOP's next delta frame, or the start of one) was that client's
        first."""
        from gi.repository import Gst

        with self._lock:
            media = self._media
            if media is None or not media.played or media.pause_id:
                return
            media.paused_at = time.monotonic()
        idle = threading.Event()

        def on_idle(pad: Any, info: Any) -> Any:
            idle.set()
            return Gst.PadProbeReturn.REMOVE

        pause_id = media.pay_sink.add_probe(Gst.PadProbeType.BLOCK_DOWNSTREAM, lambda pad, info: Gst.PadProbeReturn.OK)
        with self._lock:
            media.pause_id = pause_id
        media.pay_sink.add_probe(Gst.PadProbeType.IDLE, on_idle)
        started = time.monotonic()
        pipeline = media.media.get_element().get_parent()
        if idle.wait(PAUSE_WAIT_S) and pipeline is not None:
            # not on this thread: the server's sending thread may wait for this one (the clients' sockets)
            draining = threading.Thread(target=drain, args=(server_sinks(pipeline),), name="svelive-rtsp-drain",
                                        daemon=True)
            draining.start()
            draining.join(max(0.0, PAUSE_WAIT_S - (time.monotonic() - started)))

    def resume_payloads(self, media: _Media, older_than_s: float = 0.0) -> None:
        """Let frames through again (any thread): the PLAY was answered, or ``older_than_s`` passed since the
        pause (a PLAY that failed after :meth:`pause_payloads` is never answered)."""
        with self._lock:
            if not media.pause_id or time.monotonic() - media.paused_at < older_than_s:
                return
            pause_id, media.pause_id = media.pause_id, 0
        media.pay_sink.remove_probe(pause_id)

    def hold_until_keyframe(self, client: Any, transports: list[Any]) -> None:
        """GLib thread, ``client`` started playing (its ``transports`` are active): hold them until the next
        keyframe reaches the payloader (:meth:`_on_payload`) and ask for one (:meth:`_on_preview`), so that the
        client's first picture is a keyframe with its SPS/PPS, not the rest of a GOP it cannot decode."""
        with self._lock:
            media = self._media
            first = media is not None and not media.played
        if media is None:
            return
        pipeline = media.media.get_element().get_parent()
        if pipeline is not None:
            sinks = server_sinks(pipeline)
            with self._lock:
                media.sinks = sinks
        if first:
            # the media's first client: its first frame, x264's first and a keyframe, waits prerolled in the sink
            # for this PLAY (held, the client got the start of it, then the next keyframe: a frame cut short)
            media.played = True
            return
        for transport in transports:
            transport.set_active(False)
        with self._lock:
            if self._media is media:  # else the media went meanwhile: nothing to wait for
                media.joining[client] = list(transports)
                self._keyframe_wanted = True
        self.resume_payloads(media)

    def forget_joiner(self, client: Any) -> None:
        """GLib thread, ``client`` closed or tore its session down: never let it in."""
        with self._lock:
            if self._media is not None:
                self._media.joining.pop(client, None)

    def _on_preview(self, preview: PreviewFrame) -> None:
        """Pusher thread (and the GLib thread for a new media's first frame): hand the preview to the media's appsrc (converted to its size and kind)."""
        from gi.repository import Gst

        with self._lock:
            media = self._media
        if media is None:
            return
        self.resume_payloads(media, older_than_s=1.0)
        with self._lock:
            pts = next_pts(media_running_time(media.src), media.last_pts, round(1e9 / self.settings.fps))
            if pts is None:
                self.skipped += 1  # closer than half a frame interval to the frame before it
                return
            media.last_pts = pts
            now = time.monotonic_ns()
            keyframe = self._keyframe_wanted and now - media.last_keyframe_ns >= self.keyframe_gap_s * 1e9
            if keyframe:  # else a later frame's, once the gap has passed (or a periodic keyframe lets them in)
                self._keyframe_wanted = False
                media.last_keyframe_ns = now
                self.keyframes_forced += 1
        i420 = to_i420(self._fit(preview.image, media))
        if self.timecode and preview.signal:
            stamp_timecode(i420, int(round(preview.wall_time * 1000)))  # into the luma plane
        if keyframe:
            from gi.repository import GstVideo

            # all_headers False: x264 puts SPS/PPS in the keyframe itself; with True it also pushed them as a
            # buffer of their own, which the payloader sent as a picture with the keyframe's time stamp
            event = GstVideo.video_event_new_upstream_force_key_unit(Gst.CLOCK_TIME_NONE, False, 0)
            media.encoder.get_static_pad("src").send_event(event)
        # counted before the hand-over: appsrc may encode it (and tick ``encoded``) before emit returns
        now = time.monotonic_ns()
        self.pushed.tick(now)
        push_frame(media.src, i420.tobytes(), pts)
        if preview.signal:
            self.arrival_to_push.add((now - preview.host_time_ns) / 1e6)

    @staticmethod
    def _fit(image: np.ndarray, media: _Media) -> np.ndarray:
        """``image`` at the media's size: cropped to even sides, or resized when the frames changed size."""
        if image.shape[:2] != (media.height, media.width):
            cropped = even_size(image)
            image = cropped if cropped.shape[:2] == (media.height, media.width) else \
                cv2.resize(image, (media.width, media.height), interpolation=cv2.INTER_AREA)
        return image

    # ----- state -------------------------------------------------------
    def bitrate_kbps(self) -> float:
        """Encoded kbit/s over the last two seconds (0 when nothing was encoded in them)."""
        now = time.monotonic_ns()
        recent = [(t, n) for t, n in list(self._bytes) if now - t <= 2e9]
        if len(recent) < 2:
            return 0.0
        span = (recent[-1][0] - recent[0][0]) / 1e9
        return round(sum(n for _, n in recent[1:]) * 8 / 1000 / span, 1) if span > 0 else 0.0

    def state(self) -> dict[str, Any]:
        """The RTSP publisher's part of /api/state."""
        with self._lock:
            media, clients = self._media, self._clients
            waiting = 0 if media is None else len(media.joining)
        encoded = self.encoded.count  # read before pushed, so that a frame pushed meanwhile cannot show encoded > pushed
        pushed = self.pushed.count
        rate = None if media is None else self.settings.bitrate_for(media.width, media.height)
        return {"url": self.url, "path": self.path, "paths": list(self.paths), "auth": self.token is not None,
                "clients": clients,
                "encoding": media is not None,
                "width": None if media is None else media.width, "height": None if media is None else media.height,
                "frames_pushed": pushed, "frames_encoded": encoded, "frames_skipped": self.skipped,
                "keyframes_forced": self.keyframes_forced, "joins_at_keyframe": self.joins,
                "waiting_for_keyframe": waiting,
                "fps": round(self.encoded.rate(), 2), "bitrate_kbps": self.bitrate_kbps(),
                "arrival_to_push": self.arrival_to_push.summary(),
                "h264": {"fps": self.settings.fps, "keyframe_s": self.settings.keyframe_s,
                         "bitrate_kbps": rate,
                         "speed_preset": self.settings.speed_preset, "tune": "zerolatency", "bframes": 0}}


def _make_factory(Gst: Any, GstRtspServer: Any, description: Any) -> Any:
    """A shared-media factory whose pipeline is built from ``description()`` each time a media is made (so each
    media takes the frame size and kind of the moment)."""

    class PreviewFactory(GstRtspServer.RTSPMediaFactory):
        def do_create_element(self, url: Any) -> Any:
            return Gst.parse_launch(description())

        def do_gen_key(self, url: Any) -> str:
            # one media for every path and query (?token=) this factory is reached by: one encoding
            return "preview"

    return PreviewFactory()


def _make_auth(GstRtspServer: Any, GstRtsp: Any, token: str, role: Any) -> Any:
    """An RTSPAuth that admits a request carrying ``token`` (see :func:`token_matches`) with ``role``; others get
    401 with a basic challenge."""

    class TokenAuth(GstRtspServer.RTSPAuth):
        def __init__(self) -> None:
            super().__init__()
            # connections that showed the token: a client that sent ?token= with DESCRIBE sends its SETUP and
            # PLAY to the control URL, without the query
            self.admitted: set[Any] = set()

        def do_authenticate(self, ctx: Any) -> bool:
            result, authorization = ctx.request.get_header(GstRtsp.RTSPHeaderField.AUTHORIZATION, 0)
            query = ctx.uri.query if ctx.uri is not None else None
            client = ctx.client
            if client in self.admitted or \
                    token_matches(token, authorization if result == GstRtsp.RTSPResult.OK else None, query):
                if client is not None and client not in self.admitted:
                    self.admitted.add(client)
                    client.connect("closed", self.admitted.discard)
                ctx.set_token(role)
                return True
            return False

    auth = TokenAuth()
    auth.set_supported_methods(GstRtsp.RTSPAuthMethod.BASIC)
    return auth
