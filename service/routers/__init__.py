"""The HTTP layer: one router per area, each built over one served camera; no logic of their own."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from service.pipeline import Pipeline
from service.publishers.mjpeg import StreamHub

NO_STORE = {"Cache-Control": "no-store, no-cache, must-revalidate, max-age=0", "Pragma": "no-cache"}


@dataclass
class ServedCamera:
    """One camera of the service: its name (the ``/cam/NAME`` prefix), its pipeline, its MJPEG hub
    (made on the event loop when the server starts) and its RTSP publisher if it has one."""

    name: str
    pipeline: Pipeline
    hub: StreamHub | None = None
    rtsp: Any = None
