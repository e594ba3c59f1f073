"""GET /api/state: the state of one camera's service as JSON (assembled by ``service.publishers.state``)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter

from service.publishers.state import camera_state
from service.routers import ServedCamera
from service.settings import ServerSettings


def router(cam: ServedCamera, settings: ServerSettings) -> APIRouter:
    api = APIRouter()

    @api.get("/api/state")
    async def state() -> dict[str, Any]:
        return await camera_state(cam, settings)

    return api
