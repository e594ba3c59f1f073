"""The state of one camera's service as JSON: the pipeline's counters plus its publishers'."""

from __future__ import annotations

import asyncio
import os
from typing import Any

from fastapi import APIRouter
from starlette.concurrency import run_in_threadpool

from service.routers import ServedCamera
from service.settings import ServerSettings


def process_stats() -> dict[str, float]:
    """Resident memory (MB) and CPU time (s) of this process."""
    with open("/proc/self/statm") as f:
        rss_pages = int(f.read().split()[1])
    times = os.times()
    return {"rss_mb": round(rss_pages * os.sysconf("SC_PAGE_SIZE") / 2**20, 1),
            "cpu_s": round(times.user + times.system, 2)}


async def camera_state(cam: ServedCamera, settings: ServerSettings) -> dict[str, Any]:
    """The whole state of ``cam``: pipeline, MJPEG clients and the server process."""
    out = await run_in_threadpool(cam.pipeline.state)
    mjpeg = cam.hub.state()
    out["camera_name"] = cam.name
    out["noise"] = cam.pipeline.reconstruction.noise_state()
    out["fps"]["streamed"] = mjpeg["streamed_fps"]
    out["frames"]["streamed"] = mjpeg["streamed"]
    out["latency_ms"]["arrival_to_sent"] = mjpeg["arrival_to_sent"]
    out["clients"] = mjpeg["clients"]
    out["client_list"] = mjpeg["client_list"]
    out["drops"]["client_skipped"] = mjpeg["client_skipped"]
    if cam.rtsp is not None:
        out["rtsp"] = cam.rtsp.state()
        out["fps"]["rtsp"] = out["rtsp"]["fps"]
    out["server"] = {"tasks": len(asyncio.all_tasks()), "host": settings.host, "port": settings.port,
                     "auth": settings.token is not None, **process_stats()}
    return out


def router(cam: ServedCamera, settings: ServerSettings) -> APIRouter:
    api = APIRouter()

    @api.get("/api/state")
    async def state() -> dict[str, Any]:
        return await camera_state(cam, settings)

    return api
