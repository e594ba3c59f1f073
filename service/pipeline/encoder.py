"""The encoder stage: tone map + JPEG of the newest HdrFrame while someone watches, "no signal" frames
while the source is offline, and the hand-off of every JPEG to the listeners (the HTTP fan-out).

Colour frames (linear camera RGB) are white-balanced (fixed, or the automatic estimate smoothed over
frame time) and taken through the optional camera -> Rec.709 matrix on their way into the tone map,
which writes BGR for OpenCV's JPEG encoder; the EXR snapshot's colour is :meth:`EncoderStage.exr_image`.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import cv2
import numpy as np

from svelive.errors import SveliveError
from svelive.tonemap import ToneMapper, ToneSettings
from svelive.whitebalance import ColourSettings, WhiteBalance, WhiteBalancer, exr_output, output_matrix

from service.pipeline.config import PipelineConfig
from service.pipeline.frames import EncodedFrame, Published, monotonic_to_wall
from service.pipeline.meters import DropCounter, LatencyWindow, RateMeter


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
    """The encoder thread's loop, its listeners, watchers and snapshot requests.

    Waits on ``cond`` (shared with the reconstruction stage, which notifies it on
    every new frame) and encodes ``latest()`` once per new frame, only while a
    client watches or a snapshot is asked. ``tone``, ``colour`` and ``jpeg_quality``
    may be changed at run time (under ``cond``).
    """

    def __init__(self, config: PipelineConfig, latest: Callable[[], Published | None], online: Callable[[], bool],
                 cond: threading.Condition, drops: DropCounter, stop: threading.Event) -> None:
        self.config = config
        self._latest = latest
        self._online = online
        self._cond = cond
        self._drops = drops
        self._stop = stop
        self.tone: ToneSettings = config.tone
        self.colour: ColourSettings = config.colour
        self.jpeg_quality = config.jpeg_quality
        #: owned by the encoder thread (``update``); its ``current`` is read by the others
        self._balancer = WhiteBalancer(config.colour)
        self._encoded: EncodedFrame | None = None
        self._last_signal: EncodedFrame | None = None
        self.watchers = 0
        self._snapshot_waiters = 0
        self._listeners: list[Callable[[EncodedFrame], None]] = []
        self.encoded = RateMeter()
        self.latency = {name: LatencyWindow() for name in ("encode", "arrival_to_jpeg")}

    def run(self) -> None:
        """The encoder thread: until ``stop`` is set."""
        mapper = ToneMapper(self.tone)
        last_no_signal = 0
        seq = 0
        no_signal_period_ns = 1e9 / self.config.no_signal_fps
        while True:
            with self._cond:
                while True:
                    if self._stop.is_set():
                        return
                    latest, encoded = self._latest(), self._last_signal
                    watching = self.watchers > 0
                    encoded_hdr_seq = encoded.hdr_seq if encoded is not None else 0
                    new_frame = (watching or self._snapshot_waiters > 0) and latest is not None \
                        and latest.seq > encoded_hdr_seq
                    now = time.monotonic_ns()
                    no_signal = watching and not self._online() and now - last_no_signal >= no_signal_period_ns
                    if new_frame or no_signal:
                        break
                    self._cond.wait(timeout=0.1)
                tone, colour, quality = self.tone, self.colour, self.jpeg_quality
            if new_frame:
                if watching and encoded is not None and latest.seq > encoded_hdr_seq + 1:
                    self._drops.count("encoder_busy", latest.seq - encoded_hdr_seq - 1)
                mapper.configure(tone)
                start = time.monotonic_ns()
                display = self._resize(self._tone_map(mapper, latest, colour))
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

    def _tone_map(self, mapper: ToneMapper, latest: Published, colour: ColourSettings) -> np.ndarray:
        """The preview of one frame: uint8 (H, W), or (H, W, 3) BGR for colour (white balance and matrix applied)."""
        image, time_ns = latest.hdr.image, latest.hdr.host_time_ns
        if image.ndim == 2:
            return mapper(image, time_ns)
        self._balancer.configure(colour)
        balance = self._balancer.update(image, time_ns)
        return mapper(image, time_ns, output_matrix(balance.multipliers, colour.matrix), bgr=True)

    def white_balance(self, published: Published | None = None) -> WhiteBalance | None:
        """The white balance for ``published`` (default: the newest frame); None for mono or before a frame.

        Auto: the preview's smoothed balance while it is recent, else the frame's own
        estimate (nobody watched, so nothing was smoothed). Fixed: the multipliers. Any thread.
        """
        published = published or self._latest()
        if published is None or published.hdr.image.ndim != 3:
            return None
        return self._balancer.for_frame(published.hdr.image, published.hdr.host_time_ns, self.colour)

    def exr_image(self, published: Published) -> tuple[dict[str, np.ndarray], dict[str, object]]:
        """The EXR channels and colour attributes of a frame: ``Y`` for mono; for colour ``R``, ``G``, ``B``
        in the configured output space with the white balance in use (svelive.whitebalance.exr_output)."""
        channels, attributes = exr_output(published.hdr.image, self.white_balance(published), self.colour)
        if published.hdr.image.ndim == 3:
            attributes["cfa"] = published.camera.cfa.name if published.camera.cfa is not None else "none"
        return channels, attributes

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
            self.watchers = max(0, self.watchers + delta)
            self._cond.notify_all()

    def latest_jpeg(self) -> EncodedFrame | None:
        """The newest preview JPEG (possibly a no-signal frame), or None."""
        return self._encoded

    def snapshot_jpeg(self, timeout: float = 2.0) -> EncodedFrame | None:
        """A JPEG of the newest reconstructed frame, encoding it if nobody did; None if there is none."""
        deadline = time.monotonic() + timeout
        with self._cond:
            latest = self._latest()
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
