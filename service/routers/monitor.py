"""HDR monitoring of one camera: a pixel's radiance, the log2 histogram and the overlay map (svelive.monitor).

Each product is computed at most once per published frame (keyed by ``Published.seq``), on the first request
that asks for it, whatever the number of viewers; nothing is computed while nobody asks. The monitor holds
the newest frame and the :data:`HELD` - 1 frames before it that a request of it read, so that ``frame=ID``
can still ask about them (an EXR snapshot's frame, the frame an overlay showed).
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from fastapi import APIRouter, Query
from fastapi.responses import JSONResponse, Response
from starlette.concurrency import run_in_threadpool

from svelive import hdr_encode, monitor
from svelive.whitebalance import WhiteBalance

from service.pipeline import Pipeline
from service.pipeline.frames import Published
from service.routers import NO_STORE, ServedCamera

#: Frames the monitor holds: the newest and the ones before it that a request read.
HELD = 3


class FrameGone(Exception):
    """The frame asked for is no longer held (one line)."""


@dataclass(frozen=True)
class Basis:
    """What every product of one frame needs, made once per frame: the white balance and colour settings the
    EXR snapshot uses, the display matrix, mid-grey, the clip level and the noise floor."""

    balance: WhiteBalance | None
    colour: Any
    matrix: np.ndarray | None
    grey: float | None
    clip: float
    floor: float


class FrameProducts:
    """The held frames and what was computed of each, shared by every request of one camera; thread-safe.

    A product is computed by the first request that needs it, while later ones for the same frame and
    product wait for it (never computed twice).
    """

    def __init__(self, pipeline: Pipeline) -> None:
        self._pipeline = pipeline
        self._lock = threading.Lock()
        self._held: OrderedDict[int, Published] = OrderedDict()  # seq -> frame, oldest first
        self._products: dict[tuple[int, str], Any] = {}
        self._computing: dict[tuple[int, str], threading.Lock] = {}

    def frame(self, frame_id: int | None = None) -> Published | None:
        """The newest frame (None before the first), or the held frame with ``frame_id`` (FrameGone if none)."""
        latest = self._pipeline.latest()
        with self._lock:
            if latest is not None and latest.seq not in self._held:
                self._held[latest.seq] = latest
                while len(self._held) > HELD:
                    gone, _ = self._held.popitem(last=False)
                    for key in [key for key in self._products if key[0] == gone]:
                        del self._products[key]
            if frame_id is None or latest is None:
                return latest
            for published in reversed(self._held.values()):
                if published.hdr.frame_id == frame_id:
                    return published
            held = ", ".join(str(p.hdr.frame_id) for p in self._held.values())
        raise FrameGone(f"frame {frame_id} is no longer held; held: {held} (the newest and the "
                        f"{HELD - 1} before it that the monitor read)")

    def held(self) -> list[int]:
        """Frame ids of the held frames, oldest first."""
        with self._lock:
            return [p.hdr.frame_id for p in self._held.values()]

    def product(self, published: Published, name: str, compute: Callable[[], Any]) -> Any:
        """``compute()`` for this frame and ``name``, once."""
        key = (published.seq, name)
        with self._lock:
            if key in self._products:
                return self._products[key]
            gate = self._computing.setdefault(key, threading.Lock())
        with gate:
            with self._lock:
                if key in self._products:
                    return self._products[key]
            try:
                value = compute()
            except BaseException:
                with self._lock:  # no gate left behind by a computation that failed
                    self._computing.pop(key, None)
                raise
            with self._lock:
                if published.seq in self._held:
                    self._products[key] = value
                self._computing.pop(key, None)
            return value

    def basis(self, published: Published) -> Basis:
        """The frame's :class:`Basis`, once per frame."""
        def compute() -> Basis:
            stage = self._pipeline.colour
            balance, colour = stage.white_balance(published), stage.settings
            image, camera = published.hdr.image, published.camera
            matrix = monitor.display_matrix(balance, colour)
            return Basis(balance, colour, matrix, monitor.mid_grey(image, self._pipeline.encoder.tone, matrix),
                         monitor.clip_level(camera), monitor.noise_floor(camera))
        return self.product(published, "basis", compute)


def router(cam: ServedCamera) -> APIRouter:
    api = APIRouter()
    products = FrameProducts(cam.pipeline)

    def find(frame_id: int | None) -> Published | JSONResponse:
        try:
            published = products.frame(frame_id)
        except FrameGone as exc:
            return JSONResponse({"detail": str(exc)}, status_code=404)
        if published is None:
            return JSONResponse({"detail": "no frame yet"}, status_code=503)
        return published

    def about(published: Published) -> dict[str, Any]:
        height, width = published.hdr.image.shape[:2]
        return {"frame_id": published.hdr.frame_id, "width": width, "height": height, "held": products.held()}

    @api.get("/api/pixel")
    async def pixel(x: int = Query(...), y: int = Query(...), frame: int | None = Query(None)) -> Any:
        published = find(frame)
        if isinstance(published, JSONResponse):
            return published
        monitor.check_pixel(published.hdr.image.shape, x, y)

        def read() -> dict[str, Any]:
            basis = products.basis(published)
            hdr = published.hdr
            out = monitor.pixel_readout(hdr.image, x, y, balance=basis.balance, colour=basis.colour,
                                        grey=basis.grey, clip=basis.clip, floor=basis.floor, motion=hdr.motion,
                                        confidence=hdr.confidence_map())
            return {**about(published), **out, "space": "Y" if hdr.image.ndim == 2 else basis.colour.output_space,
                    "mid_grey": basis.grey, "clip_level": basis.clip, "noise_floor": basis.floor}

        return JSONResponse(await run_in_threadpool(read), headers=NO_STORE)

    @api.get("/api/histogram")
    async def histogram(frame: int | None = Query(None)) -> Any:
        published = find(frame)
        if isinstance(published, JSONResponse):
            return published

        def make() -> dict[str, Any]:
            basis = products.basis(published)
            result = products.product(published, "histogram", lambda: monitor.histogram(
                published.hdr.image, basis.clip, basis.floor).to_dict())
            grey = None if basis.grey is None else round(float(np.log2(basis.grey)), 4)
            return {**about(published), **result, "mid_grey_log2": grey,
                    "channels": "camera" if published.hdr.image.ndim == 3 else "Y"}

        return JSONResponse(await run_in_threadpool(make), headers=NO_STORE)

    async def hdr_snapshot(published: Published, encode: Callable[[Basis], bytes], media: str, suffix: str) -> Any:
        """One encode of ``published`` per request, off the event loop; 503 naming the extra without it."""
        if not hdr_encode.available():
            return JSONResponse({"detail": f"HDR snapshots need imagecodecs: {hdr_encode.INSTALL}"},
                                status_code=503)

        def make() -> bytes | None:
            basis = products.basis(published)
            return None if basis.grey is None else encode(basis)

        data = await run_in_threadpool(make)
        if data is None:
            return JSONResponse({"detail": "the frame has no positive pixel: no mid-grey to expose by"},
                                status_code=409)
        frame_id = published.hdr.frame_id
        return Response(data, media_type=media, headers={
            **NO_STORE, "X-Timestamp": f"{published.wall_time:.6f}", "X-Frame-Id": str(frame_id),
            "Content-Disposition": f'inline; filename="svelive-{frame_id}{suffix}"'})

    @api.get("/snapshot.avif")
    async def snapshot_avif(transfer: str = Query("pq"), bits: int = Query(10),
                            frame: int | None = Query(None)) -> Any:
        transfer, bits = hdr_encode.check_transfer(transfer), hdr_encode.check_bits(bits)
        published = find(frame)
        if isinstance(published, JSONResponse):
            return published
        return await hdr_snapshot(published, lambda basis: hdr_encode.encode_avif(
            published.hdr.image, basis.matrix, basis.grey, transfer=transfer, bits=bits), "image/avif", ".avif")

    @api.get("/snapshot.uhdr.jpg")
    async def snapshot_uhdr(frame: int | None = Query(None)) -> Any:
        published = find(frame)
        if isinstance(published, JSONResponse):
            return published
        return await hdr_snapshot(published, lambda basis: hdr_encode.encode_ultrahdr(
            published.hdr.image, basis.matrix, basis.grey), "image/jpeg", ".uhdr.jpg")

    @api.get("/api/overlay")
    async def overlay_legend() -> dict[str, Any]:
        return {**monitor.overlay_legend(), "held": products.held()}

    @api.get("/overlay.map")
    async def overlay_map(stride: int = Query(1, ge=1, le=64), frame: int | None = Query(None),
                          confidence: bool = Query(False)) -> Response:
        published = find(frame)
        if isinstance(published, JSONResponse):
            return published
        hdr = published.hdr
        sure = confidence and (hdr.confidence is not None or hdr.confidence_of is not None)
        kind = "overlay+confidence" if sure else "overlay"  # the confidence map only for those who ask

        def make() -> bytes:
            basis = products.basis(published)
            full = products.product(published, kind, lambda: monitor.overlay_map(
                hdr.image, basis.grey, basis.clip, hdr.motion, basis.matrix, hdr.confidence_map() if sure else None))
            if stride == 1:
                return full.tobytes()
            return products.product(published, f"{kind}/{stride}", lambda: full[::stride, ::stride].tobytes())

        data = await run_in_threadpool(make)
        height, width = published.hdr.image.shape[:2]
        return Response(data, media_type="application/octet-stream",
                        headers={**NO_STORE, "X-Frame-Id": str(published.hdr.frame_id),
                                 "X-Width": str(-(-width // stride)), "X-Height": str(-(-height // stride)),
                                 "X-Stride": str(stride), "X-Motion": "0" if published.hdr.motion is None else "1",
                                 "X-Confidence": "1" if sure else "0"})

    return api

