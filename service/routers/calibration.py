"""Response calibration of one camera from its live frames."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ConfigDict, Field, model_validator
from starlette.concurrency import run_in_threadpool

from service.pipeline.calibration import MAX_SWEEP, ExposureUnsupported
from service.routers import NO_STORE, ServedCamera
from svelive.calibrate.response import SWEEP_KNOTS


class CalibrateRequest(BaseModel):
    """Body of POST /api/calibrate/response (optional). ``sweep``: exposure times (the camera's
    unit, GigE: microseconds) to step through, one frame each, fitted together in the background.
    ``max_knots``: the knots of the log-spline the sweep's fit is also offered (default SWEEP_KNOTS, 0 for
    polynomials only; docs/calibration.md)."""

    model_config = ConfigDict(extra="forbid")
    max_degree: int = Field(6, ge=1, le=10)
    apply: bool = False
    sweep: list[float] | None = Field(None, min_length=1, max_length=MAX_SWEEP)
    max_knots: int | None = Field(None, ge=0, le=16)

    @model_validator(mode="after")
    def _knots_need_a_sweep(self) -> CalibrateRequest:
        if self.max_knots is not None and self.sweep is None:
            raise ValueError("max_knots needs a sweep: one frame cannot fit a log-spline (give \"sweep\")")
        return self


def router(cam: ServedCamera) -> APIRouter:
    api = APIRouter()
    pipeline = cam.pipeline

    @api.post("/api/calibrate/response")
    async def calibrate_response(request: CalibrateRequest | None = None) -> Any:
        # seconds of numpy at full HD: in a worker thread, so the streams keep flowing
        request = request or CalibrateRequest()
        if request.sweep is not None:  # a background job: 202 with it, progress in the state and GET
            try:
                job = pipeline.start_sweep(request.sweep, request.max_degree, request.apply,
                                           max_knots=SWEEP_KNOTS if request.max_knots is None
                                           else request.max_knots)
            except ExposureUnsupported as exc:
                return JSONResponse({"detail": str(exc)}, status_code=409)
            return JSONResponse(job, status_code=202, headers=NO_STORE)
        data = await run_in_threadpool(pipeline.calibration.calibrate_response, request.max_degree, request.apply)
        if data is None:
            return JSONResponse({"detail": "no frame yet"}, status_code=503)
        return JSONResponse(data, headers=NO_STORE)

    @api.get("/api/calibrate/response")
    async def last_calibration() -> Any:
        data = pipeline.calibration.last_calibration()
        if data is None:
            return JSONResponse({"detail": "no calibration yet"}, status_code=404)
        return JSONResponse(data, headers=NO_STORE)

    @api.delete("/api/calibrate/response")
    async def reset_response() -> dict[str, Any]:
        return {"response": pipeline.calibration.reset_response()}

    return api
