"""The viewer page and the MJPEG stream."""

from __future__ import annotations

import asyncio
from importlib import resources

from fastapi import APIRouter, Query, Request
from fastapi.responses import HTMLResponse, StreamingResponse

from service.publishers.mjpeg import BOUNDARY
from service.routers import NO_STORE, ServedCamera


#: Longest a stream waits for a frame before it checks whether its client left or the server is closing.
CHECK_S = 0.25


def viewer_html() -> str:
    return (resources.files("service") / "static" / "index.html").read_text(encoding="utf-8")


def router(cam: ServedCamera) -> APIRouter:
    api = APIRouter()
    page = viewer_html()
    pipeline = cam.pipeline

    @api.get("/", response_class=HTMLResponse)
    async def viewer() -> HTMLResponse:
        return HTMLResponse(page, headers=NO_STORE)

    @api.get("/stream.mjpg")
    async def stream(request: Request, fps: float | None = Query(None, gt=0, le=120)) -> StreamingResponse:
        hub = cam.hub
        min_interval = 0.0 if fps is None else 1.0 / fps
        remote = f"{request.client.host}:{request.client.port}" if request.client else "?"
        closing = getattr(request.app.state, "closing", None) or asyncio.Event()

        async def parts():
            client = hub.register(remote)
            pipeline.watch(+1)
            try:
                last = 0
                while not closing.is_set():  # the server shuts down: end the response cleanly
                    item = await hub.wait_newer(last, timeout=CHECK_S)
                    if item is None:
                        if await request.is_disconnected():
                            return
                        continue
                    yield hub.part(item)
                    hub.sent(client, item, last)
                    last = item.seq
                    if min_interval:  # a rate cap, cut short when the server closes
                        try:
                            await asyncio.wait_for(closing.wait(), min_interval)
                        except TimeoutError:
                            pass
            finally:
                pipeline.watch(-1)
                hub.clients.pop(client.id, None)

        return StreamingResponse(parts(), media_type=f"multipart/x-mixed-replace; boundary={BOUNDARY}",
                                 headers={**NO_STORE, "X-Accel-Buffering": "no"})

    return api
