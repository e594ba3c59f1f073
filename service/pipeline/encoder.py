"""The encoder stage: tone map of the newest HdrFrame while someone watches, then JPEG while MJPEG clients
watch, "no signal" frames while the source is offline; every JPEG is the newest of :attr:`EncoderStage.jpeg_port`
(the MJPEG fan-out and snapshots read it) and every tone-mapped 8-bit preview the newest of
:attr:`EncoderStage.preview_port` (RTSP reads it): the tone map runs once for both.

Colour frames (linear camera RGB) are white-balanced and taken through the optional camera -> Rec.709
matrix of the colour stage (:class:`service.pipeline.colour.ColourStage`, shared with the EXR snapshot)
on their way into the tone map, which writes BGR for OpenCV's JPEG encoder.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import cv2
import numpy as np

from service.pipeline.colour import ColourStage
from service.pipeline.config import PipelineConfig
from service.pipeline.frames import EncodedFrame, PreviewFrame, Published, monotonic_to_wall
from service.pipeline.handoff import Newest
from service.pipeline.meters import DropCounter, LatencyWindow, RateMeter
from service.pipeline.priority import EncoderPriority
from svelive.core.errors import SveliveError
from svelive.tonemap import ToneMapper, ToneSettings
from svelive.whitebalance import ColourSettings


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
    """JPEG bytes of a uint8 (H, W) grey or (H, W, 3) BGR image."""
    ok, buffer = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise SveliveError("JPEG encoding failed")
    return buffer.tobytes()


class EncoderStage:
    """The encoder thread's loop, its output ports, watchers and snapshot requests.

    Waits on ``cond`` (the condition of ``published``, the reconstruction stage's port,
    which wakes it on every new frame) and tone-maps the newest frame once while anyone
    wants it: the 8-bit preview goes to ``preview_port`` (RTSP) while
    ``preview_watchers`` > 0, and is JPEG-encoded for ``jpeg_port`` (MJPEG)
    only while ``watchers`` > 0 or a snapshot is asked, with the white balance and
    matrix of ``colour``. ``tone``, ``colour.settings`` and ``jpeg_quality`` may be
    changed at run time (under ``cond``).

    Every published frame is counted once: encoded, ``not_watched`` (skipped while
    nobody streamed: not a drop) or the drop ``encoder_busy`` (skipped while someone
    streamed, because the encoder was still busy with an earlier frame).
    """

    def __init__(self, config: PipelineConfig, published: Newest[Published], online: Callable[[], bool],
                 cond: threading.Condition, drops: DropCounter, stop: threading.Event,
                 colour: ColourStage | None = None) -> None:
        self.config = config
        self._latest = published.latest
        self._online = online
        self._cond = cond
        self._drops = drops
        self._stop = stop
        self.tone: ToneSettings = config.tone
        self.colour = colour if colour is not None else ColourStage(config.colour)
        self.jpeg_quality = config.jpeg_quality
        #: every JPEG made (no-signal ones included), newest first: the MJPEG fan-out's and the snapshots' input
        self.jpeg_port: Newest[EncodedFrame] = Newest()
        #: every preview made for the preview watchers (no-signal ones included): RTSP's input
        self.preview_port: Newest[PreviewFrame] = Newest()
        self._last_signal: EncodedFrame | None = None
        self._preview: PreviewFrame | None = None
        self.watchers = 0
        self.preview_watchers = 0
        self._snapshot_waiters = 0
        #: reconstructed frames skipped while nobody streamed (neither JPEG nor preview watchers): not drops
        self.not_watched = 0
        #: the newest Published.seq counted as encoded, not_watched or encoder_busy (under ``cond``)
        self._accounted = 0
        self.encoded = RateMeter()
        self.previews = RateMeter()
        #: the encoder thread's priority (service.pipeline.priority)
        self.priority = EncoderPriority(config.publisher_nice, config.publisher_idle)
        self.latency = {name: LatencyWindow() for name in ("tone_map", "encode", "arrival_to_jpeg")}

    def run(self) -> None:
        """The encoder thread: until ``stop`` is set."""
        self.priority.enter()
        mapper = ToneMapper(self.tone)
        last_no_signal = 0
        seq = preview_seq = 0
        no_signal_period_ns = 1e9 / self.config.no_signal_fps
        while True:
            with self._cond:
                while True:
                    if self._stop.is_set():
                        return
                    latest, encoded, mapped = self._latest(), self._last_signal, self._preview
                    streaming = self.watchers > 0 or self.preview_watchers > 0
                    want_jpeg = self.watchers > 0 or self._snapshot_waiters > 0
                    jpeg_seq = encoded.hdr_seq if encoded is not None else 0
                    mapped_seq = mapped.hdr_seq if mapped is not None else 0
                    if not streaming:
                        self._count_not_watched()
                    new_jpeg = want_jpeg and latest is not None and latest.seq > jpeg_seq
                    new_preview = self.preview_watchers > 0 and latest is not None and latest.seq > mapped_seq
                    now = time.monotonic_ns()
                    no_signal = streaming and not self._online() and now - last_no_signal >= no_signal_period_ns
                    if new_jpeg or new_preview or no_signal:
                        break
                    self._cond.wait(timeout=0.1)
                tone, colour, quality = self.tone, self.colour.settings, self.jpeg_quality
                jpeg_wanted = self.watchers > 0 or (new_jpeg and self._snapshot_waiters > 0)
                preview_wanted = self.preview_watchers > 0
                if new_jpeg or new_preview:
                    skipped = latest.seq - self._accounted - 1
                    if skipped > 0 and streaming:
                        self._drops.count("encoder_busy", skipped)
                    elif skipped > 0:
                        self.not_watched += skipped
                    self._accounted = max(self._accounted, latest.seq)
            item: EncodedFrame | None = None
            if new_jpeg or new_preview:
                start, start_cpu = time.monotonic_ns(), time.thread_time_ns()
                if latest.seq > mapped_seq:
                    mapper.configure(tone)
                    display = self._resize(self._tone_map(mapper, latest, colour))
                    display.flags.writeable = False
                    preview_seq += 1
                    mapped = PreviewFrame(preview_seq, display, True, latest.hdr.frame_id, latest.seq,
                                          latest.hdr.host_time_ns)
                    self.previews.tick()
                    self.latency["tone_map"].add((time.monotonic_ns() - start) / 1e6)
                if new_jpeg:
                    jpeg = encode_jpeg(mapped.image, quality)
                    done = time.monotonic_ns()
                    seq += 1
                    item = EncodedFrame(seq, jpeg, True, latest.hdr.frame_id, latest.seq, latest.hdr.host_time_ns,
                                        latest.wall_time, mapped.image.shape[1], mapped.image.shape[0])
                    self.latency["encode"].add((done - start) / 1e6)
                    self.latency["arrival_to_jpeg"].add((done - latest.hdr.host_time_ns) / 1e6)
                preview = mapped if new_preview else None
                self.priority.after_frame((time.monotonic_ns() - start) / 1e9,
                                          (time.thread_time_ns() - start_cpu) / 1e9)
            else:
                last_no_signal = now
                width, height = (latest.hdr.image.shape[1], latest.hdr.image.shape[0]) if latest else (640, 360)
                display = self._resize(no_signal_image(width, height))
                display.flags.writeable = False
                preview = None
                if preview_wanted:
                    preview_seq += 1
                    preview = PreviewFrame(preview_seq, display, False, None, latest.seq if latest else 0, now)
                if jpeg_wanted:
                    seq += 1
                    item = EncodedFrame(seq, encode_jpeg(display, quality), False, None, jpeg_seq, now,
                                        monotonic_to_wall(now), display.shape[1], display.shape[0])
            if item is not None:
                self.encoded.tick()
            with self._cond:  # the ports' items and the snapshots' view of them change together
                self._preview = mapped
                if preview is not None:
                    self.preview_port.put(preview)
                if item is not None:
                    if item.signal:
                        self._last_signal = item
                    self.jpeg_port.put(item)
                self._cond.notify_all()

    def _count_not_watched(self) -> None:
        """Under ``cond``, while nobody streams: count the frames published since the last one accounted as
        not watched, all but the newest (a watcher may still come for it)."""
        latest = self._latest()
        if latest is not None and latest.seq - 1 > self._accounted:
            self.not_watched += latest.seq - 1 - self._accounted
            self._accounted = latest.seq - 1

    def _tone_map(self, mapper: ToneMapper, latest: Published, colour: ColourSettings) -> np.ndarray:
        """The preview of one frame: uint8 (H, W), or (H, W, 3) BGR for colour (white balance and matrix applied)."""
        image, time_ns = latest.hdr.image, latest.hdr.host_time_ns
        matrix = self.colour.preview_matrix(latest, colour)
        return mapper(image, time_ns) if matrix is None else mapper(image, time_ns, matrix, bgr=True)

    def preview_size(self, width: int, height: int) -> tuple[int, int]:
        """(width, height) of the preview of an image of ``width`` x ``height``: scaled down to ``preview_width``
        when it is wider, else the same."""
        limit = self.config.preview_width
        if limit and width > limit:
            return limit, max(1, round(height * limit / width))
        return width, height

    def _resize(self, image: np.ndarray) -> np.ndarray:
        size = self.preview_size(image.shape[1], image.shape[0])
        if size != (image.shape[1], image.shape[0]):
            return cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        return image

    def watch(self, delta: int) -> None:
        """Add (+1) or remove (-1) a JPEG stream client; JPEGs are encoded only while there is one."""
        with self._cond:
            if self.watchers == 0 and self.preview_watchers == 0:
                self._count_not_watched()  # before the first watcher: its frames were nobody's
            self.watchers = max(0, self.watchers + delta)
            self._cond.notify_all()

    def watch_previews(self, delta: int) -> None:
        """Add (+1) or remove (-1) a preview consumer (an RTSP stream with clients); frames are tone-mapped
        for ``preview_port`` only while there is one, and JPEG-encoded only for ``watch``."""
        with self._cond:
            if self.watchers == 0 and self.preview_watchers == 0:
                self._count_not_watched()
            self.preview_watchers = max(0, self.preview_watchers + delta)
            self._cond.notify_all()

    def latest_preview(self) -> PreviewFrame | None:
        """The newest tone-mapped frame (never a no-signal one), or None before the first."""
        return self._preview

    def latest_jpeg(self) -> EncodedFrame | None:
        """The newest preview JPEG (possibly a no-signal frame), or None."""
        return self.jpeg_port.latest()

    def snapshot_jpeg(self, timeout: float = 2.0) -> EncodedFrame | None:
        """A JPEG of the newest reconstructed frame, encoding it if nobody did; None if there is none."""
        deadline = time.monotonic() + timeout
        with self._cond:
            latest = self._latest()
            if latest is None:
                return None
            encoded = self._last_signal
            if encoded is not None and encoded.hdr_seq >= latest.seq:
                return encoded
            seen = self.jpeg_port.seq  # the encoder puts under ``cond``: a JPEG of ``latest`` comes after it
            self._snapshot_waiters += 1
            self._cond.notify_all()
        try:
            while not self._stop.is_set():
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return None
                got = self.jpeg_port.get_newest(seen, min(remaining, 0.25))
                if got is not None:
                    seen, encoded = got
                    if encoded.signal and encoded.hdr_seq >= latest.seq:
                        return encoded
            return None
        finally:
            with self._cond:
                self._snapshot_waiters -= 1
