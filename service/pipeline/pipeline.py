"""The live pipeline: capture thread -> newest-frame hand-off -> reconstruction -> preview encoder.

    capture thread ──(Frame)──> NewestSlot ──> reconstruction thread ──> latest Published (HdrFrame)
                                (drops the oldest)                            │
                                                        encoder thread <──────┘  (only while someone
                                                        tone map + JPEG          watches or a snapshot
                                                          │                      is asked)
                                                          └──> listeners (the HTTP fan-out)

Each stage keeps only the newest item, so a slow stage skips frames instead
of building a queue; every skipped frame is counted by cause. Frame arrival
timestamps (``Frame.host_time_ns``, the monotonic clock) travel with the frames,
so the latency of every stage is measured against the frame's arrival.
numpy and OpenCV release the GIL, so the reconstruction and encoder threads run
on separate cores; OpenCV's own pool is limited (see :func:`opencv_threads`) so
that together they do not oversubscribe the machine.
"""

from __future__ import annotations

import collections
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np

from svelive.calibrate import Response, calibrate_frame, linearise, load_mask, load_response
from svelive.capture import Source, open_source
from svelive.errors import SveliveError
from svelive.frame import Frame, HdrFrame
from svelive.pattern import Pattern
from svelive.reconstruct import methods as method_names
from svelive.sensor import Sensor
from svelive.tonemap import ToneMapper, ToneSettings

#: Samples kept per latency / rate window.
WINDOW = 256
#: Pattern used when neither the settings nor the source name one.
FALLBACK_PATTERN = "1,4/16,64"


def opencv_threads(cpu_count: int | None = None) -> int:
    """OpenCV pool size for the pipeline: the cores minus one, at least 1.

    The reconstruction thread and the encoder thread each run on a core of their
    own; OpenCV's parallel loops inside them would otherwise compete for the same
    cores (on 2 cores: 1 thread, i.e. no OpenCV pool at all).
    """
    return max(1, (cpu_count or os.cpu_count() or 1) - 1)


@dataclass(frozen=True)
class PipelineConfig:
    """What the pipeline reconstructs and how.

    Attributes:
        source: source spec (see svelive.capture), e.g. ``"demo"`` or ``"gige:GV01"``.
        source_options: extra keyword options for ``open_source`` (e.g. fps, width).
        pattern: exposure pattern text; None: the source's own, else FALLBACK_PATTERN.
        black_level, white_level: DN overrides of the source's sensor; None keeps it.
        method: reconstruction method name; None for the default.
        temporal: use temporal fusion where the reconstructor offers it.
        response: path of a response JSON (``svelive calibrate response``): every frame
            is linearised through it before reconstruction; None: the camera is linear.
        mask: path of a mask file (``svelive calibrate mask``): its per-pixel exposure
            map replaces the nominal tile's exposures; None: the nominal pattern.
        workers: threads the reconstruction spreads one frame over; 0: one per core.
        queue: frames the capture -> reconstruction hand-off holds (1..8).
        tone: preview tone-mapping parameters.
        jpeg_quality: preview JPEG quality, 10..100.
        preview_width: downscale previews wider than this (pixels); 0 keeps full size.
        offline_after_s: no frame for this long means the source is offline.
        retry_s: wait before reopening a source that failed or went away.
        no_signal_fps: rate of "no signal" frames sent while the source is offline.
    """

    source: str = "demo"
    source_options: dict[str, Any] = field(default_factory=dict)
    pattern: str | None = None
    black_level: float | None = None
    white_level: float | None = None
    method: str | None = None
    temporal: bool = True
    response: str | None = None
    mask: str | None = None
    workers: int = 0
    queue: int = 1
    tone: ToneSettings = field(default_factory=ToneSettings)
    jpeg_quality: int = 80
    preview_width: int = 0
    offline_after_s: float = 2.0
    retry_s: float = 1.0
    no_signal_fps: float = 2.0

    def __post_init__(self) -> None:
        if self.pattern is not None:
            Pattern.parse(self.pattern)
        check_method(self.method)
        check_jpeg_quality(self.jpeg_quality)
        if not 0 <= self.workers <= 64:
            raise SveliveError(f"workers must be 0..64 (0: one per core), got {self.workers}")
        if not 1 <= self.queue <= 8:
            raise SveliveError(f"queue must hold 1..8 frames, got {self.queue}")
        if not 0 <= self.preview_width <= 16384:
            raise SveliveError(f"preview width must be 0..16384 pixels, got {self.preview_width}")
        for name in ("offline_after_s", "retry_s", "no_signal_fps"):
            if not 0 < getattr(self, name) <= 3600:
                raise SveliveError(f"{name} must be in (0, 3600], got {getattr(self, name)}")


def check_method(method: str | None) -> None:
    """Raise SveliveError unless ``method`` is None or a known reconstruction method."""
    if method is not None and method not in method_names():
        raise SveliveError(f"unknown method {method!r}; choose from {', '.join(method_names())}")


def check_jpeg_quality(quality: int) -> None:
    """Raise SveliveError unless ``quality`` is an integer JPEG quality in 10..100."""
    if isinstance(quality, bool) or not isinstance(quality, (int, np.integer)) or not 10 <= quality <= 100:
        raise SveliveError(f"JPEG quality must be an integer 10..100, got {quality!r}")


class CalibrationBusy(SveliveError):
    """A calibration was asked while another one runs."""


class NewestSlot:
    """Bounded hand-off between two threads that keeps the newest items and drops the oldest.

    ``put`` never blocks; ``get`` blocks up to a timeout. ``dropped`` counts the
    items pushed out unread.
    """

    def __init__(self, capacity: int = 1) -> None:
        self._items: collections.deque = collections.deque()
        self._capacity = capacity
        self._cond = threading.Condition()
        self._closed = False
        self.dropped = 0

    def put(self, item: Any) -> int:
        """Add ``item``; returns how many old items were dropped to make room (0 or 1)."""
        with self._cond:
            dropped = 0
            while len(self._items) >= self._capacity:
                self._items.popleft()
                dropped += 1
            self._items.append(item)
            self.dropped += dropped
            self._cond.notify()
            return dropped

    def get(self, timeout: float) -> Any | None:
        """The oldest item still held, or None after ``timeout`` seconds or once closed."""
        with self._cond:
            if not self._items and not self._closed:
                self._cond.wait(timeout)
            return self._items.popleft() if self._items else None

    def close(self) -> None:
        """Wake any waiting ``get``; later gets return what is left, then None."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()


class RateMeter:
    """Events per second over the last WINDOW events (0 when the last one is older than ``stale_s``)."""

    def __init__(self, stale_s: float = 2.0) -> None:
        self._times: collections.deque[int] = collections.deque(maxlen=WINDOW)
        self._lock = threading.Lock()
        self.count = 0
        self.stale_s = stale_s

    def tick(self, now_ns: int | None = None) -> None:
        with self._lock:
            self._times.append(time.monotonic_ns() if now_ns is None else now_ns)
            self.count += 1

    def rate(self) -> float:
        with self._lock:
            times = list(self._times)
        if len(times) < 2 or (time.monotonic_ns() - times[-1]) / 1e9 > self.stale_s:
            return 0.0
        # over the last two seconds at most, so a rate change shows quickly
        recent = [t for t in times if times[-1] - t <= 2e9]
        if len(recent) < 2:
            return 0.0
        return (len(recent) - 1) / ((recent[-1] - recent[0]) / 1e9)


class LatencyWindow:
    """Recent durations in ms of one stage, summarised as p50 / p95 / max."""

    def __init__(self) -> None:
        self._values: collections.deque[float] = collections.deque(maxlen=WINDOW)
        self._lock = threading.Lock()

    def add(self, ms: float) -> None:
        with self._lock:
            self._values.append(ms)

    def summary(self) -> dict[str, float] | None:
        with self._lock:
            values = np.array(self._values, dtype=np.float64)
        if values.size == 0:
            return None
        p50, p95 = np.percentile(values, [50, 95])
        return {"p50": round(float(p50), 2), "p95": round(float(p95), 2), "max": round(float(values.max()), 2),
                "n": int(values.size)}


class FrameReconstructor:
    """The one adapter between the pipeline and the reconstruction library.

    Linearises raw frames through a calibrated response when there is one
    (``svelive.calibrate.linearise``), then runs the stateful
    ``svelive.reconstructor.Reconstructor`` (temporal fusion, motion mask).
    ``pattern`` may carry a calibrated per-pixel exposure map.
    """

    def __init__(self, pattern: Pattern, sensor: Sensor, method: str | None, temporal: bool,
                 response: Response | None = None, workers: int = 1) -> None:
        from svelive.reconstructor import Reconstructor

        self.pattern, self.sensor, self.method, self.temporal = pattern, sensor, method, temporal
        self.response = response
        self._stateful = Reconstructor(pattern, method=method, temporal=temporal, black_level=sensor.black_level,
                                       white_level=sensor.white_level, gain=sensor.gain,
                                       read_noise=sensor.read_noise, workers=workers)

    @property
    def name(self) -> str:
        """The method really in use (with temporal fusion the default differs; see svelive.reconstructor)."""
        return self._stateful.method

    def close(self) -> None:
        """Stop the reconstructor's worker threads."""
        self._stateful.close()

    def matches(self, pattern: Pattern, sensor: Sensor, method: str | None, temporal: bool,
                response: Response | None = None) -> bool:
        return (pattern, sensor, method, temporal) == (self.pattern, self.sensor, self.method, self.temporal) \
            and response is self.response

    def __call__(self, raw: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """(image float32 (H, W) radiance, None, motion bool (H, W)) of a raw frame.

        The confidence map (None here) is not computed: nothing in the service uses
        it, and at 1920x1200 it costs several ms per frame.
        """
        if self.response is not None:
            raw = linearise(raw, self.response, self.sensor)
        result = self._stateful.process(raw)
        return result.image, None, result.motion


@dataclass(frozen=True)
class Published:
    """One reconstructed frame as the pipeline publishes it.

    Attributes:
        hdr: the HdrFrame (timings_ms holds "queue" and "reconstruct").
        seq: the pipeline's own counter of published frames.
        pattern: the exposure pattern's text form.
        sensor: the sensor the raw frame came from.
        published_ns: monotonic time it was published.
    """

    hdr: HdrFrame
    seq: int
    pattern: str
    sensor: Sensor
    published_ns: int

    @property
    def wall_time(self) -> float:
        """The frame's arrival time as Unix seconds (for X-Timestamp and EXR attributes)."""
        return monotonic_to_wall(self.hdr.host_time_ns)


def monotonic_to_wall(monotonic_ns: int) -> float:
    """Unix time in seconds of a ``time.monotonic_ns()`` reading."""
    return (time.time_ns() - time.monotonic_ns() + monotonic_ns) / 1e9


@dataclass(frozen=True)
class EncodedFrame:
    """One preview JPEG, shared by every client.

    Attributes:
        seq: the encoder's counter (increases by one per JPEG, no-signal ones included).
        jpeg: the JPEG file.
        signal: False for a "no signal" placeholder.
        frame_id: the source frame id (None for no-signal frames).
        hdr_seq: the Published.seq it was made from (-1 for no-signal frames).
        host_time_ns: arrival time of the source frame (its creation time for no-signal frames).
        wall_time: the same as Unix seconds.
        width, height: pixels.
    """

    seq: int
    jpeg: bytes
    signal: bool
    frame_id: int | None
    hdr_seq: int
    host_time_ns: int
    wall_time: float
    width: int
    height: int


def no_signal_image(width: int = 640, height: int = 360) -> np.ndarray:
    """A dark grey uint8 (height, width) frame with "NO SIGNAL" centred."""
    image = np.full((height, width), 40, np.uint8)
    text, font = "NO SIGNAL", cv2.FONT_HERSHEY_SIMPLEX
    scale = max(width, 160) / 400.0
    thickness = max(1, int(round(scale * 2)))
    (tw, th), _ = cv2.getTextSize(text, font, scale, thickness)
    cv2.putText(image, text, ((width - tw) // 2, (height + th) // 2), font, scale, 200, thickness, cv2.LINE_AA)
    return image


def encode_jpeg(image: np.ndarray, quality: int) -> bytes:
    """JPEG bytes of a uint8 (H, W) image."""
    ok, buffer = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise SveliveError("JPEG encoding failed")
    return buffer.tobytes()


class Pipeline:
    """Runs the capture, reconstruction and encoder threads of one source.

    ``source_factory`` builds a new (unopened) Source each time the pipeline
    (re)connects; by default ``open_source(config.source, ...)``.
    """

    def __init__(self, config: PipelineConfig, source_factory: Callable[[], Source] | None = None) -> None:
        self.config = config
        self._factory = source_factory or self._default_factory
        self._stop = threading.Event()
        self._slot = NewestSlot(config.queue)
        self._cond = threading.Condition()  # guards the fields below and wakes the encoder
        self._method = config.method
        self._tone = config.tone
        self._jpeg_quality = config.jpeg_quality
        self._latest: Published | None = None
        self._encoded: EncodedFrame | None = None
        self._last_signal: EncodedFrame | None = None
        self._watchers = 0
        self._snapshot_waiters = 0
        self._listeners: list[Callable[[EncodedFrame], None]] = []
        self._source: Source | None = None
        self._source_state = "starting"
        self._source_error: str | None = None
        self._source_stats: dict[str, Any] = {}
        self._closed_source_drops: collections.Counter = collections.Counter()
        self._pattern_text: str | None = None
        self._last_frame_ns: int | None = None
        self._drops: collections.Counter = collections.Counter()
        self._motion_fraction: float | None = None
        self._reconstruct_error: str | None = None
        self.captured = RateMeter()
        self.reconstructed = RateMeter()
        self.encoded = RateMeter()
        self.latency = {name: LatencyWindow() for name in
                        ("queue", "reconstruct", "arrival_to_hdr", "encode", "arrival_to_jpeg")}
        self._threads: list[threading.Thread] = []
        self._started_ns = time.monotonic_ns()
        self._newest_raw: tuple[Frame, str] | None = None
        # the configured response and mask are read now, so a bad file fails before serving
        self._configured_response = load_response(config.response) if config.response else None
        self._response = self._configured_response
        self._response_origin = config.response
        self._pixel_map = load_mask(config.mask) if config.mask else None
        self._calibration: dict[str, Any] | None = None
        self._calibrating = threading.Lock()
        self.workers = config.workers or os.cpu_count() or 1

    # ----- lifecycle ---------------------------------------------------
    def start(self) -> Pipeline:
        """Start the three threads; returns self."""
        if self._threads:
            return self
        cv2.setNumThreads(opencv_threads())
        for name, target in (("capture", self._capture_loop), ("reconstruct", self._reconstruct_loop),
                             ("encode", self._encode_loop)):
            thread = threading.Thread(target=target, name=f"svelive-{name}", daemon=True)
            thread.start()
            self._threads.append(thread)
        return self

    def stop(self, timeout: float = 5.0) -> None:
        """Stop the threads and close the source (idempotent)."""
        self._stop.set()
        source = self._source
        if source is not None:
            source.close()
        self._slot.close()
        with self._cond:
            self._cond.notify_all()
        for thread in self._threads:
            thread.join(timeout)
        self._threads = []

    def __enter__(self) -> Pipeline:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _default_factory(self) -> Source:
        c = self.config
        return open_source(c.source, pattern=c.pattern, black_level=c.black_level, white_level=c.white_level,
                           **c.source_options)

    # ----- capture -----------------------------------------------------
    def _capture_loop(self) -> None:
        while not self._stop.is_set():
            source: Source | None = None
            try:
                source = self._factory()
                self._source = source
                if self._stop.is_set():
                    break
                source.open()
                pattern = self.config.pattern or source.pattern or FALLBACK_PATTERN
                self._pattern_text = str(Pattern.parse(pattern))
                self._source_state, self._source_error = "online", None
                for frame in source:
                    self.captured.tick(frame.host_time_ns)
                    self._last_frame_ns = frame.host_time_ns
                    self._newest_raw = (frame, self._pattern_text)
                    if self._slot.put((frame, self._pattern_text)):
                        self._count_drop("reconstruct_busy")
                    self._source_stats = source.stats()
                if self._stop.is_set():
                    break
                self._source_stats = source.stats()
                if self._source_stats.get("state") == "ended":
                    self._source_state = "ended"
                    return
                self._source_state = "offline"
            except Exception as exc:  # a camera that fails or vanishes: report, retry
                self._source_state = "offline"
                self._source_error = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            finally:
                if source is not None:
                    try:
                        self._source_stats = source.stats()
                    except Exception:
                        pass
                    source.close()
                    self._closed_source_drops.update(self._source_stats.get("drops", {}))
                    self._source_stats = {**self._source_stats, "drops": {}}
                self._source = None
            self._stop.wait(self.config.retry_s)

    def _count_drop(self, cause: str, n: int = 1) -> None:
        with self._cond:
            self._drops[cause] += n

    def online(self) -> bool:
        """True while a source is connected and delivered a frame within ``offline_after_s``."""
        if self._source_state != "online" or self._last_frame_ns is None:
            return False
        if self._source_stats and self._source_stats.get("online") is False:
            return False
        return (time.monotonic_ns() - self._last_frame_ns) / 1e9 <= self.config.offline_after_s

    # ----- reconstruction ----------------------------------------------
    def _reconstruct_loop(self) -> None:
        adapter: FrameReconstructor | None = None
        patterns: dict[str, Pattern] = {}  # one Pattern per text: a per-pixel map is compared by identity
        seq = 0
        try:
            while not self._stop.is_set():
                item = self._slot.get(timeout=0.2)
                if item is None:
                    continue
                frame, pattern_text = item
                frame: Frame
                start_ns = time.monotonic_ns()
                method, response = self._method, self._response
                try:
                    pattern = patterns.get(pattern_text)
                    if pattern is None:
                        pattern = Pattern.parse(pattern_text)
                        if self._pixel_map is not None:
                            pattern = pattern.with_pixel_map(self._pixel_map)
                        patterns = {pattern_text: pattern}
                    if adapter is None or not adapter.matches(pattern, frame.sensor, method, self.config.temporal,
                                                              response):
                        if adapter is not None:
                            adapter.close()
                        adapter = FrameReconstructor(pattern, frame.sensor, method, self.config.temporal, response,
                                                     self.workers)
                    image, confidence, motion = adapter(frame.raw)
                except Exception as exc:
                    self._reconstruct_error = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                    self._count_drop("reconstruct_error")
                    if adapter is not None:
                        adapter.close()
                    adapter = None
                    continue
                done_ns = time.monotonic_ns()
                self._reconstruct_error = None
                timings = {"queue": (start_ns - frame.host_time_ns) / 1e6, "reconstruct": (done_ns - start_ns) / 1e6}
                hdr = HdrFrame(image=image, confidence=confidence, frame_id=frame.frame_id,
                               host_time_ns=frame.host_time_ns, device_time_ns=frame.device_time_ns,
                               method=adapter.name, motion=motion, timings_ms=timings)
                if motion is not None:
                    self._motion_fraction = float(np.count_nonzero(motion)) / motion.size
                seq += 1
                published = Published(hdr, seq, pattern_text, frame.sensor, done_ns)
                self.reconstructed.tick(done_ns)
                self.latency["queue"].add(timings["queue"])
                self.latency["reconstruct"].add(timings["reconstruct"])
                self.latency["arrival_to_hdr"].add((done_ns - frame.host_time_ns) / 1e6)
                with self._cond:
                    self._latest = published
                    self._cond.notify_all()
        finally:
            if adapter is not None:
                adapter.close()

    def latest(self) -> Published | None:
        """The newest reconstructed frame (an immutable record), or None before the first."""
        return self._latest

    # ----- encoder -----------------------------------------------------
    def _encode_loop(self) -> None:
        mapper = ToneMapper(self._tone)
        last_no_signal = 0
        seq = 0
        no_signal_period_ns = 1e9 / self.config.no_signal_fps
        while True:
            with self._cond:
                while True:
                    if self._stop.is_set():
                        return
                    latest, encoded = self._latest, self._last_signal
                    watching = self._watchers > 0
                    encoded_hdr_seq = encoded.hdr_seq if encoded is not None else 0
                    new_frame = (watching or self._snapshot_waiters > 0) and latest is not None \
                        and latest.seq > encoded_hdr_seq
                    now = time.monotonic_ns()
                    no_signal = watching and not self.online() and now - last_no_signal >= no_signal_period_ns
                    if new_frame or no_signal:
                        break
                    self._cond.wait(timeout=0.1)
                tone, quality = self._tone, self._jpeg_quality
            if new_frame:
                if watching and encoded is not None and latest.seq > encoded_hdr_seq + 1:
                    self._count_drop("encoder_busy", latest.seq - encoded_hdr_seq - 1)
                mapper.configure(tone)
                start = time.monotonic_ns()
                display = self._resize(mapper(latest.hdr.image, latest.hdr.host_time_ns))
                jpeg = encode_jpeg(display, quality)
                done = time.monotonic_ns()
                seq += 1
                item = EncodedFrame(seq, jpeg, True, latest.hdr.frame_id, latest.seq, latest.hdr.host_time_ns,
                                    latest.wall_time, display.shape[1], display.shape[0])
                self.latency["encode"].add((done - start) / 1e6)
                self.latency["arrival_to_jpeg"].add((done - latest.hdr.host_time_ns) / 1e6)
            else:
                last_no_signal = now
                width, height = (latest.hdr.image.shape[1], latest.hdr.image.shape[0]) if latest else (640, 360)
                display = self._resize(no_signal_image(width, height))
                seq += 1
                item = EncodedFrame(seq, encode_jpeg(display, quality), False, None, encoded_hdr_seq, now,
                                    monotonic_to_wall(now), display.shape[1], display.shape[0])
            self.encoded.tick()
            with self._cond:
                self._encoded = item
                if item.signal:
                    self._last_signal = item
                listeners = list(self._listeners)
                self._cond.notify_all()
            for listener in listeners:
                listener(item)

    def _resize(self, image: np.ndarray) -> np.ndarray:
        width = self.config.preview_width
        if width and image.shape[1] > width:
            height = max(1, round(image.shape[0] * width / image.shape[1]))
            return cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
        return image

    def add_listener(self, callback: Callable[[EncodedFrame], None]) -> None:
        """Call ``callback(EncodedFrame)`` from the encoder thread for every new JPEG."""
        with self._cond:
            self._listeners.append(callback)

    def remove_listener(self, callback: Callable[[EncodedFrame], None]) -> None:
        with self._cond:
            if callback in self._listeners:
                self._listeners.remove(callback)

    def watch(self, delta: int) -> None:
        """Add (+1) or remove (-1) a stream client; the encoder runs only while there is one."""
        with self._cond:
            self._watchers = max(0, self._watchers + delta)
            self._cond.notify_all()

    def latest_jpeg(self) -> EncodedFrame | None:
        """The newest preview JPEG (possibly a no-signal frame), or None."""
        return self._encoded

    def snapshot_jpeg(self, timeout: float = 2.0) -> EncodedFrame | None:
        """A JPEG of the newest reconstructed frame, encoding it if nobody did; None if there is none."""
        deadline = time.monotonic() + timeout
        with self._cond:
            latest = self._latest
            if latest is None:
                return None
            self._snapshot_waiters += 1
            self._cond.notify_all()
            try:
                while not self._stop.is_set():
                    encoded = self._last_signal
                    if encoded is not None and encoded.hdr_seq >= latest.seq:
                        return encoded
                    remaining = deadline - time.monotonic()
                    if remaining <= 0:
                        return None
                    self._cond.wait(remaining)
                return None
            finally:
                self._snapshot_waiters -= 1

    # ----- calibration -------------------------------------------------
    def latest_raw(self) -> tuple[Frame, str] | None:
        """The newest captured raw frame and its pattern text, or None before the first."""
        return self._newest_raw

    def calibrate_response(self, max_degree: int = 6, apply: bool = False) -> dict[str, Any] | None:
        """Fit the camera's response to the newest raw frame (``svelive.calibrate.calibrate_frame``).

        Runs on the caller's thread (seconds at full HD: call it off the event loop).
        With ``apply`` the response linearises every frame from the next one on (in
        memory: a restart goes back to the configured ``response``). Returns the
        response JSON with ``curve``, ``frame_id`` and ``applied``; None when no
        frame has arrived yet. Raises SveliveError when the frame cannot calibrate
        (the response in use is kept) and CalibrationBusy while another runs.
        """
        if not 1 <= max_degree <= 10:
            raise SveliveError(f"max_degree must be 1..10, got {max_degree}")
        item = self._newest_raw
        if item is None:
            return None
        if not self._calibrating.acquire(blocking=False):
            raise CalibrationBusy("a response calibration is already running")
        try:
            frame, pattern_text = item
            data = calibrate_frame(frame.raw, Pattern.parse(pattern_text), frame.sensor, max_degree=max_degree)
        finally:
            self._calibrating.release()
        data.update(frame_id=frame.frame_id, applied=bool(apply))
        self._calibration = data
        if apply:
            with self._cond:
                self._response, self._response_origin = Response.from_dict(data), "calibrated live"
        return data

    def last_calibration(self) -> dict[str, Any] | None:
        """The result of the last successful calibrate_response, or None."""
        return self._calibration

    def reset_response(self) -> dict[str, Any] | None:
        """Go back to the configured response (the ``response`` file, or none); returns response_state()."""
        with self._cond:
            self._response, self._response_origin = self._configured_response, self.config.response
        return self.response_state()

    def response_state(self) -> dict[str, Any] | None:
        """The response in use: origin (file path or "calibrated live"), degree, coefficients, domain; None if linear."""
        with self._cond:
            response, origin = self._response, self._response_origin
        if response is None:
            return None
        return {"origin": origin, "degree": response.degree, "coefficients": list(response.coefficients),
                "domain": list(response.domain)}

    # ----- settings ----------------------------------------------------
    def settings(self) -> dict[str, Any]:
        """The settings that can be changed at run time."""
        return {"method": self._method or method_names()[0], "jpeg_quality": self._jpeg_quality,
                "tone": dict(vars(self._tone))}

    def update_settings(self, method: str | None = None, jpeg_quality: int | None = None,
                        tone: dict[str, float] | None = None) -> dict[str, Any]:
        """Change method, JPEG quality and tone-mapping parameters (all checked first); returns settings()."""
        check_method(method)
        if jpeg_quality is not None:
            check_jpeg_quality(jpeg_quality)
        new_tone = self._tone
        if tone:
            unknown = sorted(set(tone) - set(vars(new_tone)))
            if unknown:
                raise SveliveError(f"unknown tone mapping setting(s) {', '.join(unknown)}; "
                                   f"accepted: {', '.join(vars(new_tone))}")
            new_tone = replace(new_tone, **tone)
        with self._cond:
            if method is not None:
                self._method = method
            if jpeg_quality is not None:
                self._jpeg_quality = int(jpeg_quality)
            self._tone = new_tone
            self._cond.notify_all()
        return self.settings()

    # ----- state -------------------------------------------------------
    def state(self) -> dict[str, Any]:
        """Pipeline state as a JSON-ready dict (see docs/service.md)."""
        with self._cond:
            drops = dict(self._drops)
            watchers = self._watchers
        source_drops = collections.Counter(self._closed_source_drops)
        source_drops.update(self._source_stats.get("drops", {}))
        for cause, n in source_drops.items():
            drops[f"source_{cause}"] = n
        latest = self._latest
        online = self.online()
        return {
            "source": {
                "spec": self.config.source,
                "state": "online" if online else ("ended" if self._source_state == "ended" else "offline"),
                "online": online,
                "error": self._source_error,
                "width": None if latest is None else int(latest.hdr.image.shape[1]),
                "height": None if latest is None else int(latest.hdr.image.shape[0]),
                "pixel_format": self._source_stats.get("pixel_format"),
                "reconnects": self._source_stats.get("reconnects"),
            },
            "fps": {"captured": round(self.captured.rate(), 2), "reconstructed": round(self.reconstructed.rate(), 2),
                    "encoded": round(self.encoded.rate(), 2)},
            "frames": {"captured": self.captured.count, "reconstructed": self.reconstructed.count,
                       "encoded": self.encoded.count,
                       "last_frame_id": None if latest is None else latest.hdr.frame_id},
            "drops": drops,
            "dropped": sum(drops.values()),
            "latency_ms": {name: window.summary() for name, window in self.latency.items()},
            "method": self._method or method_names()[0],
            "methods": method_names(),
            "temporal": self.config.temporal,
            "motion_fraction": self._motion_fraction,
            "response": self.response_state(),
            "mask": self.config.mask,
            "workers": self.workers,
            "reconstruct_error": self._reconstruct_error,
            "pattern": self._pattern_text,
            "sensor": None if latest is None else {"bits": latest.sensor.bits,
                                                   "black_level": latest.sensor.black_level,
                                                   "white_level": latest.sensor.white_level},
            "tone": dict(vars(self._tone)),
            "jpeg_quality": self._jpeg_quality,
            "preview_width": self.config.preview_width,
            "watchers": watchers,
            "opencv_threads": cv2.getNumThreads(),
            "uptime_s": round((time.monotonic_ns() - self._started_ns) / 1e9, 1),
        }
