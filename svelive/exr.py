"""OpenEXR reading and writing: files (written to a temporary name, then renamed) and bytes.

Images go in as named 2-D channels: a monochrome frame as ``Y``, a colour frame
as ``R``, ``G``, ``B`` (:func:`image_channels`). What the colour channels mean
(camera RGB or Rec.709, the white balance) is said by attributes
(svelive.whitebalance.exr_attributes); Rec.709 data carries the standard
``chromaticities`` attribute (:data:`REC709_CHROMATICITIES`).
"""

from __future__ import annotations

import io
import os
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Mapping

import numpy as np
import OpenEXR

from svelive.core.atomic import atomic_path
from svelive.core.errors import SveliveError
from svelive.core.version import __version__

if TYPE_CHECKING:
    from svelive.core.camera import Camera

#: Rec. 709 / sRGB primaries: luminance from linear RGB.
LUMA_WEIGHTS = (0.2126, 0.7152, 0.0722)

#: The standard ``chromaticities`` attribute of Rec. 709 primaries and a D65 white:
#: (red x, y, green x, y, blue x, y, white x, y).
REC709_CHROMATICITIES = (0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290)

#: Shapes of numeric attributes stored as OpenEXR vectors and matrices (V2f, V3f, M33f).
_VECTOR_SHAPES = ((2,), (3,), (3, 3))

#: What a reconstructed pixel value is, in the ``units`` attribute of every EXR svelive writes.
UNITS = "(raw - black) / exposure, DN at relative exposure 1"

#: The attribute vocabulary of every HDR frame svelive writes (the CLI, the service's snapshots,
#: reconstruct-sequence): one name for each piece of information (:func:`standard_attributes`).
#: Colour attributes (white balance, colour space, chromaticities) come from svelive.whitebalance.
STANDARD_ATTRIBUTES: dict[str, str] = {
    "svelive": "version of svelive that wrote the file",
    "units": f"what a pixel value is: {UNITS} (per channel for colour, camera RGB before white balance)",
    "method": "reconstruction method (svelive methods)",
    "pattern": "exposure pattern, text form (rows by '/', values by ',')",
    "cfa": "colour filter layout of a colour camera (absent for a monochrome one)",
    "blackLevel": "black level, DN",
    "whiteLevel": "white (saturation) level, DN",
    "frameId": "frame number of a stream or recording (absent for a single frame)",
    "timestamp": "the frame's time, seconds as text with 6 decimals: Unix time in the service, the recording's "
                 "frame time (device clock when there is one, else the host's monotonic clock) for recorded frames",
}

_COMPRESSIONS = {
    "none": OpenEXR.NO_COMPRESSION,
    "zip": OpenEXR.ZIP_COMPRESSION,
    "zips": OpenEXR.ZIPS_COMPRESSION,
    "piz": OpenEXR.PIZ_COMPRESSION,
}


def _build(channels: Mapping[str, np.ndarray], attributes: Mapping[str, object] | None,
           half: bool, compression: str) -> OpenEXR.File:
    if not channels:
        raise SveliveError("an EXR needs at least one channel")
    if compression not in _COMPRESSIONS:
        raise SveliveError(f"unknown EXR compression {compression!r}; choose from {', '.join(_COMPRESSIONS)}")
    dtype = np.float16 if half else np.float32
    shapes = {np.shape(a) for a in channels.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise SveliveError(f"EXR channels must be 2-D arrays of one shape, got {sorted(shapes)}")
    header: dict[str, object] = {
        "compression": _COMPRESSIONS[compression],
        "type": OpenEXR.scanlineimage,
    }
    for key, value in (attributes or {}).items():
        header[key] = _attribute(key, value)
    data = {name: np.ascontiguousarray(np.asarray(a, dtype=np.float32).astype(dtype, copy=False))
            for name, a in channels.items()}
    return OpenEXR.File(header, data)


def _attribute(key: str, value: object) -> object:
    """A header value the bindings store with its type: numbers and text as they are, ``chromaticities`` as
    its 8 numbers, numeric arrays of shape (2,), (3,), (3, 3) as float32 vectors and matrices; else ``str()``."""
    if isinstance(value, (int, float, str)):
        return value
    if key == "chromaticities":
        numbers = tuple(float(x) for x in np.asarray(value, np.float64).reshape(-1))
        if len(numbers) != 8:
            raise SveliveError(f"EXR chromaticities need 8 numbers (rx, ry, gx, gy, bx, by, wx, wy), got {len(numbers)}")
        return numbers
    if isinstance(value, (tuple, list, np.ndarray)) and np.shape(value) in _VECTOR_SHAPES:
        array = np.asarray(value)
        if array.dtype.kind in "iuf":
            return array.astype(np.float32)
    return str(value)


def standard_attributes(camera: Camera, method: str, *, frame_id: int | None = None,
                        timestamp: float | None = None, extra: Mapping[str, object] | None = None) -> dict[str, object]:
    """The header attributes of an HDR frame (:data:`STANDARD_ATTRIBUTES`), then ``extra``.

    Args:
        camera: the frame's camera (its pattern, colour filter and sensor levels are recorded).
        method: the reconstruction method.
        frame_id: the frame's number in its stream, or None for a single frame.
        timestamp: the frame's time in seconds, or None (stored as text: a float attribute is float32).
        extra: more attributes (colour, noise, motion...), added last; they may not rename a standard one.
    """

    sensor = camera.sensor
    out: dict[str, object] = {"svelive": __version__, "units": UNITS, "method": str(method),
                              "pattern": "unknown" if camera.pattern is None else str(camera.pattern),
                              "blackLevel": float(sensor.black_level), "whiteLevel": float(sensor.white_level)}
    if camera.cfa is not None:
        out["cfa"] = camera.cfa.name
    if frame_id is not None:
        out["frameId"] = int(frame_id)
    if timestamp is not None:
        out["timestamp"] = f"{float(timestamp):.6f}"
    for key, value in (extra or {}).items():
        if key in STANDARD_ATTRIBUTES and key in out and value != out[key]:
            raise SveliveError(f"EXR attribute {key!r} is a standard one, set by standard_attributes: pass it as "
                               "an argument instead")
        out[key] = value
    return out


def image_channels(image: np.ndarray) -> dict[str, np.ndarray]:
    """The EXR channels of an image: ``{"Y": image}`` for (H, W), ``R``, ``G``, ``B`` for (H, W, 3)."""
    image = np.asarray(image)
    if image.ndim == 2:
        return {"Y": image}
    if image.ndim == 3 and image.shape[2] == 3:
        return {name: image[:, :, c] for c, name in enumerate("RGB")}
    raise SveliveError(f"an EXR image must be (H, W) or (H, W, 3), got shape {image.shape}")


def compress_on(threads: int | None = None) -> int:
    """Let OpenEXR compress the blocks of each file on ``threads`` threads (None: one per core);
    returns the count set. A process-wide setting of the library, off (0: the caller's thread)
    by default: a 1920x1200 frame's ZIP compression is most of the cost of writing it (measured
    443 ms on the caller's thread, 286 on two). The bytes written do not depend on it. Set it where
    one process writes a stream of files (``reconstruct``, ``reconstruct-sequence``, ``serve``), not
    in worker processes that share the cores with each other."""
    count = (os.cpu_count() or 1) if threads is None else threads
    if count < 0:
        raise SveliveError(f"EXR threads must be >= 0, got {count}")
    OpenEXR.set_global_thread_count(count)
    return count


def write_exr(path: str | os.PathLike, channels: Mapping[str, np.ndarray], attributes: Mapping[str, object] | None = None,
              *, half: bool = False, compression: str = "zip") -> Path:
    """Write named 2-D channels (float32, or half with ``half=True``) to ``path``.

    The file appears complete or not at all: it is written to a temporary name in
    the same directory and renamed. String, int and float attributes are stored as
    they are, ``chromaticities`` as the standard attribute (8 numbers), numeric
    arrays of shape (2,), (3,) or (3, 3) as float32 vectors or matrices; anything
    else as its ``str()``.
    """
    exr = _build(channels, attributes, half, compression)
    with atomic_path(path) as tmp:
        exr.write(str(tmp))
    return Path(path)


def exr_bytes(channels: Mapping[str, np.ndarray], attributes: Mapping[str, object] | None = None,
              *, half: bool = False, compression: str = "zip") -> bytes:
    """The EXR file that :func:`write_exr` would write, as bytes in memory."""
    exr = _build(channels, attributes, half, compression)
    stream = io.BytesIO()
    try:
        exr.write(stream)
    except TypeError:  # bindings older than stream support: go through a temporary file
        with tempfile.TemporaryDirectory() as tmp:
            name = os.path.join(tmp, "frame.exr")
            exr.write(name)
            return Path(name).read_bytes()
    return stream.getvalue()


def read_exr(source: str | os.PathLike | bytes) -> tuple[dict[str, np.ndarray], dict[str, object]]:
    """Channels (float32, split per channel: ``R``, ``G``, ``B``, ``Y``...) and header of an EXR file or bytes."""
    try:
        if isinstance(source, (bytes, bytearray)):
            f = OpenEXR.File(io.BytesIO(source), separate_channels=True)
        else:
            if not Path(source).is_file():
                raise SveliveError(f"{source}: no such EXR file")
            f = OpenEXR.File(str(source), separate_channels=True)
        channels = {name: np.asarray(ch.pixels, dtype=np.float32) for name, ch in f.channels().items()}
        return channels, dict(f.header())
    except SveliveError:
        raise
    except Exception as exc:  # the bindings raise plain exceptions on unreadable input
        raise SveliveError(f"{source if not isinstance(source, bytes) else 'EXR bytes'}: not a readable EXR ({exc})") from None


def read_luminance(source: str | os.PathLike | bytes) -> np.ndarray:
    """Linear luminance (float32 HxW) of an EXR: ``Y`` if present, else Rec. 709 from R, G, B."""
    channels, _ = read_exr(source)
    if "Y" in channels:
        return channels["Y"]
    if all(c in channels for c in "RGB"):
        r, g, b = (channels[c] for c in "RGB")
        return (LUMA_WEIGHTS[0] * r + LUMA_WEIGHTS[1] * g + LUMA_WEIGHTS[2] * b).astype(np.float32)
    raise SveliveError(f"{source}: EXR has neither a Y channel nor R, G, B (channels: {', '.join(channels)})")


def read_rgb(source: str | os.PathLike | bytes) -> np.ndarray:
    """Linear RGB (float32 (H, W, 3)) of an EXR: ``R``, ``G``, ``B``, or a grey image from ``Y`` alone."""
    channels, _ = read_exr(source)
    if all(c in channels for c in "RGB"):
        return np.dstack([channels[c] for c in "RGB"])
    if "Y" in channels:
        return np.repeat(channels["Y"][:, :, None], 3, axis=2)
    raise SveliveError(f"{source if not isinstance(source, bytes) else 'EXR bytes'}: EXR has neither R, G, B "
                       f"nor a Y channel (channels: {', '.join(channels)})")
