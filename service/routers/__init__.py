"""The HTTP layer: one router per area, each built over one served camera; no logic of their own."""

from __future__ import annotations

from dataclasses import dataclass

from service.pipeline import Pipeline
from service.publishers.mjpeg import StreamHub
from service.publishers.rtsp import RtspPublisher

NO_STORE = {"Cache-Control": "no-store, no-cache, must-revalidate, max-age=0", "Pragma": "no-cache"}


@dataclass
class ServedCamera:
    """One camera of the service: its name (the ``/cam/NAME`` prefix), its pipeline, its MJPEG hub
    and its RTSP publisher if it has one (both made by the app's lifespan when the server starts)."""

    name: str
    pipeline: Pipeline
    hub: StreamHub | None = None
    rtsp: RtspPublisher | None = None
