"""The run-time settings of one camera: GET and PUT /api/settings."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from pydantic import BaseModel, ConfigDict, Field

from service.routers import ServedCamera
from svelive.core.errors import SveliveError


class ToneUpdate(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    exposure_ev: float | None = Field(None, ge=-16, le=16)
    key: float | None = Field(None, ge=0.01, le=0.9)
    white_percentile: float | None = Field(None, ge=50, le=100)
    adapt_s: float | None = Field(None, ge=0, le=60)


class SettingsUpdate(BaseModel):
    """Body of PUT /api/settings: any subset of the run-time settings.

    The colour settings are checked by svelive.whitebalance.ColourSettings (one-line
    messages): ``white_balance`` "auto" or [r, g, b]; ``colour_matrix`` 9 numbers, 3 rows
    of 3, or null (none); ``output_space`` "camera" or "rec709".
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    method: str | None = Field(None, max_length=64)
    jpeg_quality: int | None = Field(None, ge=10, le=100)
    tone: ToneUpdate | None = None
    white_balance: str | list[Any] | None = None
    colour_matrix: str | list[Any] | None = None
    output_space: str | None = Field(None, max_length=16)

    def colour(self) -> dict[str, Any]:
        """The colour settings given (``colour_matrix`` null counts: it removes the matrix)."""
        given = {name: getattr(self, name) for name in ("white_balance", "colour_matrix", "output_space")
                 if name in self.model_fields_set}
        if given.get("white_balance", "") is None or given.get("output_space", "") is None:
            raise SveliveError("white_balance and output_space cannot be null: give \"auto\" or three "
                               "multipliers, and \"camera\" or \"rec709\"")
        return given


def router(cam: ServedCamera) -> APIRouter:
    api = APIRouter()
    pipeline = cam.pipeline

    @api.get("/api/settings")
    async def get_settings() -> dict[str, Any]:
        return pipeline.settings()

    @api.put("/api/settings")
    async def put_settings(update: SettingsUpdate) -> dict[str, Any]:
        tone = update.tone.model_dump(exclude_none=True) if update.tone else None
        return pipeline.update_settings(method=update.method, jpeg_quality=update.jpeg_quality, tone=tone,
                                        colour=update.colour())

    return api
