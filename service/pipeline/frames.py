"""The records the stages hand on: :class:`Published` (reconstructed), :class:`PreviewFrame` (the tone-mapped
8-bit preview) and :class:`EncodedFrame` (preview JPEG)."""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from svelive.core.camera import Camera
from svelive.core.frame import HdrFrame
from svelive.noise import NoiseEstimate


@dataclass(frozen=True)
class Published:
    """One reconstructed frame as the pipeline publishes it.

    Attributes:
        hdr: the HdrFrame (timings_ms holds "queue" and "reconstruct"; ``camera`` the
            camera it was reconstructed with).
        seq: the pipeline's own counter of published frames.
        published_ns: monotonic time it was published.
        noise: the noise model it was reconstructed with (source, uncertainty; for the EXR's attributes),
            or None.
    """

    hdr: HdrFrame
    seq: int
    published_ns: int
    noise: NoiseEstimate | None = None

    @property
    def camera(self) -> Camera:
        """The camera the frame was reconstructed with (pattern, colour filter, sensor, response)."""
        assert self.hdr.camera is not None
        return self.hdr.camera

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


@dataclass(frozen=True)
class PreviewFrame:
    """One tone-mapped 8-bit preview image, before JPEG, handed to the video publishers (RTSP).

    Attributes:
        seq: the encoder's counter of previews (no-signal ones included).
        image: uint8 (H, W) grey or (H, W, 3) BGR, read-only (shared by every publisher and the JPEG).
        signal: False for a "no signal" placeholder.
        frame_id: the source frame id (None for no-signal frames).
        hdr_seq: the Published.seq it was made from (the last one seen, for no-signal frames).
        host_time_ns: arrival time of the source frame (monotonic clock; creation time for no-signal frames).
    """

    seq: int
    image: np.ndarray
    signal: bool
    frame_id: int | None
    hdr_seq: int
    host_time_ns: int

    @property
    def wall_time(self) -> float:
        """``host_time_ns`` as Unix seconds."""
        return monotonic_to_wall(self.host_time_ns)
