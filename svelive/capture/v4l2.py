"""V4L2 devices through OpenCV's ``CAP_V4L2`` backend in raw mode, as ``v4l2:/dev/videoN``.

OpenCV is asked for the fourcc (``CAP_PROP_FOURCC``) with RGB conversion off
(``CAP_PROP_CONVERT_RGB = 0``); it then returns each frame as a flat byte
buffer, which :func:`svelive.core.formats.unpack` decodes with the frame
width, height and the row stride (bytes per line: the driver's, or the tight
row size when the buffer has no padding). Formats: GREY, Y10, Y12, Y16, Y10P,
Y12P, Y10B and the 8/10/12/16-bit Bayer fourccs. V4L2 gives no device
timestamp through OpenCV, so ``device_time_ns`` is None; ``CAP_PROP_POS_MSEC``
is kept when the driver reports one.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from svelive.capture import build_sensor, make_config
from svelive.capture.source import Source
from svelive.core import formats
from svelive.core.errors import SveliveError
from svelive.core.frame import Frame
from svelive.core.sensor import Sensor


@dataclass(frozen=True)
class V4l2Config:
    """Device settings (None keeps the driver's current value).

    Attributes:
        pixel_format: fourcc (e.g. "Y12 ", "GREY", "RG16") or PFNC name with a V4L2 alias.
        width, height: frame size in pixels.
        fps: frame rate, frames per second.
        exposure: CAP_PROP_EXPOSURE in the driver's units.
        gain: CAP_PROP_GAIN in the driver's units.
        n_buffers: driver buffers (CAP_PROP_BUFFERSIZE).
    """

    pixel_format: str | None = None
    width: int | None = None
    height: int | None = None
    fps: float | None = None
    exposure: float | None = None
    gain: float | None = None
    n_buffers: int = 4


def frame_from_buffer(buf: np.ndarray, width: int, height: int, fmt: formats.PixelFormat,
                      stride: int | None = None) -> np.ndarray:
    """Decode OpenCV's raw V4L2 buffer (uint8, any shape) into uint8/uint16 (height, width).

    The stride is ``stride`` when given, else the buffer's size over ``height``
    when that is a whole number of bytes per row, else tight rows.
    """
    data = np.ascontiguousarray(buf).reshape(-1)
    if stride is None and data.size % height == 0 and fmt.packing == "none":
        stride = data.size // height
    if stride is not None and stride == fmt.row_bytes(width):
        stride = None if fmt.packing != "none" else stride
    return formats.unpack(data, width, height, fmt, stride)


class V4l2Source(Source):
    """A V4L2 device; see the module docstring."""

    def __init__(self, spec: str, arg: str | None, *, pattern: str | None = None, sensor: Sensor | None = None,
                 bits: int | None = None, black_level: float | None = None, white_level: float | None = None,
                 cfa: str | None = None, **opts: Any) -> None:
        super().__init__(spec, pattern=pattern, sensor=sensor, cfa=cfa)
        self.config: V4l2Config = make_config(V4l2Config, opts, spec)
        self.device = arg or ""
        self._sensor_opts = (sensor, bits, black_level, white_level)
        self._cap: Any = None
        self._n = 0
        self._io = threading.Lock()

    def _open(self) -> None:
        c = self.config
        if not Path(self.device).exists():
            raise SveliveError(f"{self.device}: no such V4L2 device")
        cap = cv2.VideoCapture(self.device, cv2.CAP_V4L2)
        if not cap.isOpened():
            raise SveliveError(f"{self.device}: OpenCV's V4L2 backend cannot open it")
        if c.pixel_format:
            fmt = formats.lookup(c.pixel_format.strip() or c.pixel_format)
            code = (fmt.aliases[0] if fmt.aliases else fmt.name).ljust(4)[:4]
            cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter.fourcc(*code))
        cap.set(cv2.CAP_PROP_CONVERT_RGB, 0)
        if hasattr(cv2, "CAP_PROP_READ_TIMEOUT_MSEC"):  # a stalled device returns instead of blocking
            cap.set(cv2.CAP_PROP_READ_TIMEOUT_MSEC, 1000)
        for prop, value in ((cv2.CAP_PROP_FRAME_WIDTH, c.width), (cv2.CAP_PROP_FRAME_HEIGHT, c.height),
                            (cv2.CAP_PROP_FPS, c.fps), (cv2.CAP_PROP_EXPOSURE, c.exposure),
                            (cv2.CAP_PROP_GAIN, c.gain), (cv2.CAP_PROP_BUFFERSIZE, c.n_buffers)):
            if value is not None:
                cap.set(prop, float(value))
        fourcc = formats.fourcc_text(int(cap.get(cv2.CAP_PROP_FOURCC)))
        try:
            self._format = formats.lookup(fourcc)
        except SveliveError:
            cap.release()
            raise SveliveError(f"{self.device}: delivers fourcc {fourcc!r}, not a raw format this reads "
                               f"(choose one with pixel_format=, e.g. GREY, Y12, Y16, RG16)") from None
        self._size = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        try:
            self._settle_camera(build_sensor(*self._sensor_opts, default_bits=self._format.bits), self._format.cfa,
                                self._format.name)
        except SveliveError:
            cap.release()
            raise
        self._cap = cap

    def _close(self) -> None:
        with self._io:  # never release the device under a read in progress
            if self._cap is not None:
                self._cap.release()
                self._cap = None

    def _next(self) -> Frame | None:
        with self._io:
            if self._cap is None:
                return None
            ok, buf = self._cap.read()
        host = time.monotonic_ns()
        if not ok or buf is None:
            self._drop("read_failed")
            self._wait(self.poll_s)
            return None
        w, h = self._size
        try:
            raw = frame_from_buffer(buf, w, h, self._format)
        except SveliveError:
            self._drop("size_mismatch")
            return None
        pos = self._cap.get(cv2.CAP_PROP_POS_MSEC)
        self._n += 1
        return Frame(raw=raw, frame_id=self._n - 1, host_time_ns=host,
                     device_time_ns=int(pos * 1e6) if pos and pos > 0 else None,
                     pixel_format=self._format.name, camera=self.camera)

    def _extra_stats(self) -> dict[str, Any]:
        return {"device": self.device}
