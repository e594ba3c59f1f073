"""OpenEXR reading and writing: files (written to a temporary name, then renamed) and bytes."""

from __future__ import annotations

import io
import os
import tempfile
from pathlib import Path
from typing import Mapping

import numpy as np
import OpenEXR

from svelive.atomic import atomic_path
from svelive.errors import SveliveError

#: Rec. 709 / sRGB primaries: luminance from linear RGB.
LUMA_WEIGHTS = (0.2126, 0.7152, 0.0722)

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
        header[key] = value if isinstance(value, (int, float, str)) else str(value)
    data = {name: np.ascontiguousarray(np.asarray(a, dtype=np.float32).astype(dtype, copy=False))
            for name, a in channels.items()}
    return OpenEXR.File(header, data)


def write_exr(path: str | os.PathLike, channels: Mapping[str, np.ndarray], attributes: Mapping[str, object] | None = None,
              *, half: bool = False, compression: str = "zip") -> Path:
    """Write named 2-D channels (float32, or half with ``half=True``) to ``path``.

    The file appears complete or not at all: it is written to a temporary name in
    the same directory and renamed. String, int and float attributes are stored as
    header attributes; anything else as its ``str()``.
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
