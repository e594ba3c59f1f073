"""The EXR of a reconstructed frame: the one recipe every command, route and runner writes it with.

White balance -> output space -> attributes -> write (svelive.exr: to a temporary name, then
renamed; or bytes for an HTTP answer). The white balance in use is the caller's (a single frame
estimates its own, :func:`single_frame_balance`; a stream smooths it over time; the service's
snapshot takes the preview's); everything after it is here:

- the image's channels, ``Y`` or ``R``, ``G``, ``B`` in the output space (svelive.whitebalance.exr_output),
  then the extra planes (``confidence``, ``motion``);
- the attributes: svelive.exr.standard_attributes of the frame (:class:`FrameInfo`), its extra
  attributes (noise model, moving fraction...), then the colour ones (white balance, colour space).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from svelive.core.camera import Camera
from svelive.exr import exr_bytes, standard_attributes, write_exr
from svelive.whitebalance import ColourSettings, WhiteBalance, WhiteBalancer, exr_output


@dataclass(frozen=True)
class FrameInfo:
    """What the EXR of a frame says about it beside its pixels.

    Attributes:
        camera: the camera it was reconstructed with.
        method: the reconstruction method.
        frame_id: its number in its stream, or None for a single frame.
        timestamp: its time in seconds, or None.
        attributes: more attributes (noise model, moving fraction...), after the standard ones.
    """

    camera: Camera
    method: str
    frame_id: int | None = None
    timestamp: float | None = None
    attributes: Mapping[str, object] = field(default_factory=dict)


def single_frame_balance(image: np.ndarray, colour: ColourSettings,
                         valid: np.ndarray | None = None) -> WhiteBalance | None:
    """The white balance of a frame on its own: the fixed one, or its estimate from its ``valid`` pixels;
    None for a monochrome (H, W) image."""
    return WhiteBalancer(colour).update(image, 0, valid) if image.ndim == 3 else None


def frame_exr(image: np.ndarray, info: FrameInfo, colour: ColourSettings, balance: WhiteBalance | None,
              planes: Mapping[str, np.ndarray] | None = None) -> tuple[dict[str, np.ndarray], dict[str, object]]:
    """(channels, attributes) of a frame's EXR.

    Args:
        image: float32 (H, W), or (H, W, 3) linear camera RGB.
        info: the frame's camera, method, number, time and extra attributes.
        colour: white balance, colour matrix and output space settings.
        balance: the white balance in use (None for a monochrome image).
        planes: more 2-D channels, after the image's (``confidence``, ``motion``).
    """
    channels, colour_attributes = exr_output(image, balance, colour)
    attributes = standard_attributes(info.camera, info.method, frame_id=info.frame_id, timestamp=info.timestamp,
                                     extra={**info.attributes, **colour_attributes})
    return {**channels, **(planes or {})}, attributes


def write_frame_exr(path: str | os.PathLike, image: np.ndarray, info: FrameInfo, colour: ColourSettings,
                    balance: WhiteBalance | None, planes: Mapping[str, np.ndarray] | None = None, *,
                    half: bool = False) -> Path:
    """Write a frame's EXR (:func:`frame_exr`) to ``path``, complete or not at all; float32, or half."""
    channels, attributes = frame_exr(image, info, colour, balance, planes)
    return write_exr(path, channels, attributes, half=half)


def frame_exr_bytes(image: np.ndarray, info: FrameInfo, colour: ColourSettings, balance: WhiteBalance | None,
                    planes: Mapping[str, np.ndarray] | None = None, *, half: bool = False) -> bytes:
    """The file :func:`write_frame_exr` would write, as bytes in memory."""
    channels, attributes = frame_exr(image, info, colour, balance, planes)
    return exr_bytes(channels, attributes, half=half)
