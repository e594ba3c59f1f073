"""Image-sequence source: 8/16-bit single-channel PNG, TIFF or PGM files in name order.

Files hold raw mosaics; their colour filter is what the user gives (``cfa``, or a
Bayer ``pixel_format`` name), none by default.

Files are ordered by natural name order (``f2.png`` before ``f10.png``). Frames
come at ``fps`` (None: as fast as they are read) and, with ``loop``, start
again after the last. Every file must have the size and bit depth of the
first; a colour or differently sized file is a one-line error naming it.
"""

from __future__ import annotations

import glob
import math
import os
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from svelive.capture import build_sensor, make_config
from svelive.capture.source import EndOfStream, Source
from svelive.core import formats
from svelive.core.errors import SveliveError
from svelive.core.frame import Frame
from svelive.core.sensor import Sensor, container_bits

EXTENSIONS = (".png", ".tif", ".tiff", ".pgm")
#: Largest image decoded: 2^28 pixels (16384 x 16384; a 100-megapixel sensor's frame fits). A header
#: claiming more is refused before OpenCV allocates anything.
MAX_IMAGE_PIXELS = 1 << 28
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


@dataclass(frozen=True)
class ImagesConfig:
    """Options of the image-sequence source.

    Attributes:
        fps: delivery rate in frames per second; None or 0 for as fast as possible.
        loop: start again after the last file.
        pixel_format: name recorded in each Frame (default by file depth: Mono8 or Mono16, or
            BayerRG8/BayerRG16... with a Bayer ``cfa``); a Bayer name sets the colour filter.
    """

    fps: float | None = None
    loop: bool = False
    pixel_format: str | None = None


def natural_key(path: str) -> list:
    """Sort key: digit runs compare as numbers."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", os.path.basename(path))]


def list_images(spec: str) -> list[str]:
    """The image files named by a directory or a glob, in natural name order."""
    p = Path(spec)
    if p.is_dir():
        files = [str(f) for f in p.iterdir() if f.suffix.lower() in EXTENSIONS and f.is_file()]
        where = f"directory {spec}"
    else:
        files = [f for f in glob.glob(spec) if os.path.isfile(f)]
        where = f"{spec!r}"
    if not files:
        raise SveliveError(f"no image files in {where} (looking for {', '.join(EXTENSIONS)})")
    return sorted(files, key=natural_key)


def _pnm_header(data: bytes) -> tuple[int, int, int, int] | None:
    """(width, height, maxval, header length) of a binary PGM/PPM (``P5``/``P6``) header, or None."""
    match = re.match(rb"P[56](?:\s+|#[^\n]*\n)+(\d+)(?:\s+|#[^\n]*\n)+(\d+)(?:\s+|#[^\n]*\n)+(\d+)\s", data)
    if match is None:
        return None
    return int(match[1]), int(match[2]), int(match[3]), match.end()


def check_image_header(path: str | os.PathLike, max_pixels: int = MAX_IMAGE_PIXELS) -> None:
    """Refuse, with one line, a PNG or binary PGM whose header claims more than ``max_pixels`` pixels or
    more sample bytes than the file holds; other files pass (the decoder judges them)."""
    try:
        with open(path, "rb") as f:
            head = f.read(1024)
            size = os.fstat(f.fileno()).st_size
    except OSError as exc:
        raise SveliveError(f"{path}: cannot read ({exc.strerror})") from None
    if head.startswith(_PNG_SIGNATURE) and len(head) >= 24 and head[12:16] == b"IHDR":
        width, height = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
        need = 0
    else:
        pnm = _pnm_header(head)
        if pnm is None:
            return
        width, height, maxval, start = pnm
        channels = 3 if head[1:2] == b"6" else 1
        need = start + width * height * channels * (1 if maxval < 256 else 2)
    if width * height > max_pixels:
        raise SveliveError(f"{path}: the header claims {width}x{height} pixels, more than the {max_pixels} "
                           f"(about {math.isqrt(max_pixels)}^2) a raw frame may have")
    if need > size:
        raise SveliveError(f"{path}: the header claims {width}x{height} pixels but the file holds only {size} "
                           "bytes (truncated?)")


def decode_image(path: str | os.PathLike, what: str) -> np.ndarray:
    """An image file as OpenCV decodes it, unchanged (any dtype and channels); a one-line SveliveError
    ``"<path>: not a readable <what> image"`` when it cannot, or when its header claims an absurd size."""
    check_image_header(path)
    try:
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        reason = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        raise SveliveError(f"{path}: not a readable {what} image ({reason})") from None
    if img is None:
        raise SveliveError(f"{path}: not a readable {what} image")
    return img


def read_image(path: str) -> np.ndarray:
    """One single-channel image file as uint8 or uint16 (H, W)."""
    img = decode_image(path, "PNG, TIFF or PGM")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim != 2:
        raise SveliveError(f"{path}: has {img.shape[2]} channels; a raw SVE frame is a single-channel image")
    if img.dtype not in (np.uint8, np.uint16):
        raise SveliveError(f"{path}: {img.dtype} samples; only 8- or 16-bit integer images are raw frames")
    return img


class ImageSequenceSource(Source):
    """Frames from image files; see the module docstring."""

    def __init__(self, spec: str, arg: str | None, *, pattern: str | None = None, sensor: Sensor | None = None,
                 bits: int | None = None, black_level: float | None = None, white_level: float | None = None,
                 cfa: str | None = None, **opts: Any) -> None:
        super().__init__(spec, pattern=pattern, sensor=sensor, cfa=cfa)
        self.config: ImagesConfig = make_config(ImagesConfig, opts, spec)
        self._glob = arg or ""
        self._sensor_opts = (sensor, bits, black_level, white_level)
        self._files: list[str] = []
        self._pos = 0
        self._n = 0
        self._t0 = 0.0
        self._shape: tuple[tuple[int, ...], np.dtype] | None = None

    def _open(self) -> None:
        self._files = list_images(self._glob)
        first = read_image(self._files[0])
        self._shape = (first.shape, first.dtype)
        default_bits = container_bits(first.dtype)
        # image files do not say whether a colour filter sat on the sensor: only the user does, by a
        # format name or by --cfa (frames then carry the Bayer name of the container, e.g. BayerRG16)
        named = formats.find(self.config.pixel_format) if self.config.pixel_format else None
        self._settle_camera(build_sensor(*self._sensor_opts, default_bits=default_bits),
                            None if named is None else named.cfa, None if named is None else named.name)
        self._format = self.config.pixel_format or formats.unpacked_name(default_bits, self.camera.cfa)
        self._t0 = time.monotonic()

    def _next(self) -> Frame | None:
        if self._pos >= len(self._files):
            if not self.config.loop:
                raise EndOfStream
            self._pos = 0
        if self.config.fps:
            due = self._t0 + self._n / self.config.fps
            if not self._wait(due - time.monotonic()):
                return None
        path = self._files[self._pos]
        img = read_image(path)
        assert self._shape is not None
        if (img.shape, img.dtype) != self._shape:
            (h, w), dt = self._shape
            raise SveliveError(f"{path}: is {img.shape[1]}x{img.shape[0]} {img.dtype} but the sequence started "
                               f"with {w}x{h} {dt}")
        self._pos += 1
        frame = Frame(raw=img, frame_id=self._n, host_time_ns=time.monotonic_ns(), device_time_ns=None,
                      pixel_format=self._format, camera=self.camera)
        self._n += 1
        return frame

    def _extra_stats(self) -> dict[str, Any]:
        return {"files": len(self._files), "position": self._pos}
