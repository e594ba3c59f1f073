"""Snapshots: the newest preview as JPEG, the newest HDR frame as OpenEXR."""

from __future__ import annotations

from fastapi import APIRouter, Query
from fastapi.responses import JSONResponse, Response
from starlette.concurrency import run_in_threadpool

from svelive.frame_exr import FrameInfo

from service.routers import NO_STORE, ServedCamera


def router(cam: ServedCamera) -> APIRouter:
    api = APIRouter()
    pipeline = cam.pipeline

    @api.get("/snapshot.jpg")
    async def snapshot_jpg() -> Response:
        item = await run_in_threadpool(pipeline.snapshot_jpeg, 2.0)
        if item is None:
            return JSONResponse({"detail": "no frame yet"}, status_code=503)
        return Response(item.jpeg, media_type="image/jpeg",
                        headers={**NO_STORE, "X-Timestamp": f"{item.wall_time:.6f}", "X-Frame-Id": str(item.frame_id)})

    @api.get("/snapshot.exr")
    async def snapshot_exr(half: bool = Query(False), confidence: bool = Query(False)) -> Response:
        published = pipeline.latest()  # one immutable record: never torn between two frames
        if published is None:
            return JSONResponse({"detail": "no frame yet"}, status_code=503)
        hdr = published.hdr
        info = FrameInfo(published.camera, hdr.method, frame_id=hdr.frame_id, timestamp=published.wall_time,
                         attributes={} if published.noise is None else published.noise.attributes())
        # white balance (the preview's), output space and compression off the event loop
        data = await run_in_threadpool(pipeline.colour.exr_bytes, published, info, half=half, confidence=confidence)
        return Response(data, media_type="image/x-exr",
                        headers={**NO_STORE, "X-Timestamp": f"{published.wall_time:.6f}",
                                 "X-Frame-Id": str(hdr.frame_id),
                                 "Content-Disposition": f'attachment; filename="svelive-{hdr.frame_id}.exr"'})

    return api
