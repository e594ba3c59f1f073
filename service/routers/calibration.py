"""Response calibration of one camera from its live frames."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ConfigDict, Field
from starlette.concurrency import run_in_threadpool

from service.routers import NO_STORE, ServedCamera


class CalibrateRequest(BaseModel):
    """Body of POST /api/calibrate/response (optional)."""

    model_config = ConfigDict(extra="forbid")
    max_degree: int = Field(6, ge=1, le=10)
    apply: bool = False


def router(cam: ServedCamera) -> APIRouter:
    api = APIRouter()
    pipeline = cam.pipeline

    @api.post("/api/calibrate/response")
    async def calibrate_response(request: CalibrateRequest | None = None) -> Any:
        # seconds of numpy at full HD: in a worker thread, so the streams keep flowing
        request = request or CalibrateRequest()
        data = await run_in_threadpool(pipeline.calibrate_response, request.max_degree, request.apply)
        if data is None:
            return JSONResponse({"detail": "no frame yet"}, status_code=503)
        return JSONResponse(data, headers=NO_STORE)

    @api.get("/api/calibrate/response")
    async def last_calibration() -> Any:
        data = pipeline.last_calibration()
        if data is None:
            return JSONResponse({"detail": "no calibration yet"}, status_code=404)
        return JSONResponse(data, headers=NO_STORE)

    @api.delete("/api/calibrate/response")
    async def reset_response() -> dict[str, Any]:
        return {"response": pipeline.reset_response()}

    return api
