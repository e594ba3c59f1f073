"""Snapshots: the newest frame as one file, OpenEXR (the HDR frame) or JPEG (its preview).

The EXR is made here from the pipeline's ``hdr_port`` (one immutable :class:`Published`, never torn
between two frames): its metadata (the camera, method, frame id and time, and the noise model's
attributes), the colour stage's white balance (the preview's, so the EXR and the preview agree) and
output space, and the encoding, written by ``svelive.frame_exr`` as every EXR is. The JPEG is the
encoder's: the newest preview JPEG of ``jpeg_port`` if it shows the newest frame, else one made for the
snapshot (``Pipeline.snapshot_jpeg``). Both block (the EXR's compression, the JPEG's wait): call them
off the event loop.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from service.pipeline import ColourStage, Pipeline, Published
from svelive.frame_exr import FrameInfo, frame_exr_bytes


@dataclass(frozen=True)
class Snapshot:
    """One snapshot file and what its answer says of it.

    Attributes:
        data: the file's bytes.
        media_type: ``image/x-exr`` or ``image/jpeg``.
        frame_id: the source frame's id.
        wall_time: the frame's arrival, Unix seconds.
        filename: the name offered for saving it (EXR), or None (shown inline).
    """

    data: bytes
    media_type: str
    frame_id: int | None
    wall_time: float
    filename: str | None = None

    def headers(self) -> dict[str, str]:
        """X-Timestamp, X-Frame-Id and, with a filename, Content-Disposition."""
        out = {"X-Timestamp": f"{self.wall_time:.6f}", "X-Frame-Id": str(self.frame_id)}
        if self.filename is not None:
            out["Content-Disposition"] = f'attachment; filename="{self.filename}"'
        return out


def frame_info(published: Published) -> FrameInfo:
    """The EXR metadata of ``published``: its camera, method, frame id, arrival time and noise model."""
    hdr = published.hdr
    return FrameInfo(published.camera, hdr.method, frame_id=hdr.frame_id, timestamp=published.wall_time,
                     attributes={} if published.noise is None else published.noise.attributes())


def exr_bytes(published: Published, colour: ColourStage, *, half: bool = False, confidence: bool = False) -> bytes:
    """The EXR of ``published`` in the colour stage's output space, with the preview's white balance (any thread);
    with ``confidence`` also its "confidence" channel where the frame has one (``HdrFrame.confidence_map``)."""
    settings = colour.settings
    sure = published.hdr.confidence_map() if confidence else None
    planes = None if sure is None else {"confidence": sure}
    return frame_exr_bytes(published.hdr.image, frame_info(published), settings, colour.white_balance(published),
                           planes, half=half)


def exr_snapshot(pipeline: Pipeline, *, half: bool = False, confidence: bool = False,
                 timeout: float = 2.0) -> Snapshot | None:
    """The newest reconstructed frame of ``pipeline`` as OpenEXR (waiting up to ``timeout`` s for the first while
    the camera is starting: ``Pipeline.latest``); None if there is none."""
    published = pipeline.latest(timeout)
    if published is None:
        return None
    frame_id = published.hdr.frame_id
    return Snapshot(exr_bytes(published, pipeline.colour, half=half, confidence=confidence), "image/x-exr",
                    frame_id, published.wall_time, f"svelive-{frame_id}.exr")


def jpeg_snapshot(pipeline: Pipeline, timeout: float = 2.0) -> Snapshot | None:
    """A JPEG of the newest reconstructed frame of ``pipeline`` (waiting up to ``timeout`` s in all for the first
    frame while the camera is starting, and for the encoder); None if there is none."""
    deadline = time.monotonic() + timeout
    if pipeline.latest(timeout) is None:
        return None
    item = pipeline.snapshot_jpeg(max(deadline - time.monotonic(), 0.0))
    if item is None:
        return None
    return Snapshot(item.jpeg, "image/jpeg", item.frame_id, item.wall_time)
