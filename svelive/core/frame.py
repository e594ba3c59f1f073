"""The two records that flow through the pipeline: a raw Frame in, an HdrFrame out."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from svelive.core.camera import Camera
from svelive.core.sensor import Sensor


@dataclass(frozen=True)
class Frame:
    """One mosaicked raw frame as a source delivers it. Treat as immutable.

    Attributes:
        raw: uint8 or uint16 array (H, W), the sensor values in DN.
        frame_id: the source's frame counter (device frame id where the camera has one).
        host_time_ns: host ``time.monotonic_ns()`` when the frame was received.
        device_time_ns: the camera's own timestamp in ns, or None when it has none.
        pixel_format: the wire format it was decoded from, e.g. ``"Mono12Packed"``.
        camera: what the frame is: exposure pattern, colour filter, sensor, response
            (svelive.core.camera.Camera). Reconstruction reads it from here.
        exposure_time: the camera's global exposure time for this frame in its own unit
            (GigE: microseconds), None when the source cannot tell. Recordings keep it.
    """

    raw: np.ndarray
    frame_id: int
    host_time_ns: int
    device_time_ns: int | None = None
    pixel_format: str = "Mono16"
    camera: Camera = field(default_factory=Camera)
    exposure_time: float | None = None

    @property
    def sensor(self) -> Sensor:
        """The camera's sensor: bit depth, black and white level of the values in ``raw``."""
        return self.camera.sensor


@dataclass(frozen=True)
class HdrFrame:
    """One reconstructed HDR frame, with where it came from and what it cost.

    Attributes:
        image: float32 (H, W), or (H, W, 3) linear camera RGB for a colour camera,
            radiance in DN at relative exposure 1.
        confidence: float32 (H, W) in [0, 1]; 0 where the value is only a lower bound; None when not made
            (a live frame's is made on first use from ``confidence_of``: :meth:`confidence_map`).
        motion: bool (H, W) or None, pixels flagged as moving.
        frame_id, host_time_ns, device_time_ns: copied from the source Frame.
        method: the reconstruction method's name.
        timings_ms: per-stage durations, e.g. {"reconstruct": 12.3}.
        confidence_of: makes the confidence map when ``confidence`` is None (the live path: most frames are
            never asked for it, and a 1920x1200 map costs several ms), or None.
    """

    image: np.ndarray
    confidence: np.ndarray | None
    frame_id: int
    host_time_ns: int
    device_time_ns: int | None = None
    method: str = ""
    motion: np.ndarray | None = None
    timings_ms: dict[str, float] = field(default_factory=dict)
    camera: Camera | None = None
    confidence_of: Callable[[], np.ndarray] | None = field(default=None, repr=False, compare=False)

    def confidence_map(self) -> np.ndarray | None:
        """``confidence``, or the map ``confidence_of`` makes (once: later calls return the same array); None
        when the frame has neither."""
        return self.confidence if self.confidence is not None else self._made_confidence

    @cached_property
    def _made_confidence(self) -> np.ndarray | None:
        return None if self.confidence_of is None else self.confidence_of()
