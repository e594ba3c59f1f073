"""GET /metrics: every camera's state in the Prometheus exposition format."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import Response
from starlette.concurrency import run_in_threadpool

from service.publishers.metrics import CONTENT_TYPE_LATEST, exposition, families
from service.publishers.state import camera_state, latency_histograms
from service.routers import ServedCamera
from service.settings import ServerSettings


def router(cameras: list[ServedCamera], settings: ServerSettings) -> APIRouter:
    api = APIRouter()

    @api.get("/metrics")
    async def metrics() -> Response:
        snapshots = {cam.name: await camera_state(cam, settings) for cam in cameras}
        histograms = {cam.name: latency_histograms(cam) for cam in cameras}
        body = await run_in_threadpool(lambda: exposition(families(snapshots, histograms)))
        return Response(body, media_type=CONTENT_TYPE_LATEST)

    return api
