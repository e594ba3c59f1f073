"""Snapshots: the newest preview as JPEG, the newest HDR frame as OpenEXR (made by ``service.publishers.snapshot``)."""

from __future__ import annotations

from fastapi import APIRouter, Query
from fastapi.responses import JSONResponse, Response
from starlette.concurrency import run_in_threadpool

from service.publishers.snapshot import Snapshot, exr_snapshot, jpeg_snapshot
from service.routers import NO_STORE, ServedCamera


def answer(snapshot: Snapshot | None) -> Response:
    """The snapshot's file with its headers, or 503 before the first frame."""
    if snapshot is None:
        return JSONResponse({"detail": "no frame yet"}, status_code=503)
    return Response(snapshot.data, media_type=snapshot.media_type, headers={**NO_STORE, **snapshot.headers()})


def router(cam: ServedCamera) -> APIRouter:
    api = APIRouter()
    pipeline = cam.pipeline

    @api.get("/snapshot.jpg")
    async def snapshot_jpg() -> Response:
        return answer(await run_in_threadpool(jpeg_snapshot, pipeline, 2.0))

    @api.get("/snapshot.exr")
    async def snapshot_exr(half: bool = Query(False), confidence: bool = Query(False)) -> Response:
        # white balance (the preview's), output space and compression off the event loop
        return answer(await run_in_threadpool(exr_snapshot, pipeline, half=half, confidence=confidence))

    return api
