"""The FastAPI app: viewer page, MJPEG stream, snapshots, state and settings.

Fan-out: the encoder thread hands every new JPEG to :class:`StreamHub`, which
lives on the event loop. Each stream client is an async generator that, after
every part it sends, takes the newest JPEG there is: a slow client skips
frames (counted) and never builds a queue; the socket's own buffer is the only
backlog. A client that goes away ends its generator, which frees its record.
"""

from __future__ import annotations

import asyncio
import hmac
import itertools
import os
import socket
import time
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from importlib import resources
from typing import Any
from urllib.parse import parse_qs

from fastapi import FastAPI, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import HTMLResponse, JSONResponse, Response, StreamingResponse
from pydantic import BaseModel, ConfigDict, Field
from starlette.concurrency import run_in_threadpool

from svelive.errors import SveliveError
from svelive.exr import exr_bytes

from service.pipeline import CalibrationBusy, EncodedFrame, LatencyWindow, Pipeline, RateMeter
from service.settings import MAX_TOKEN_LENGTH, ServerSettings

BOUNDARY = "svelive-frame"
#: Largest request body accepted (the settings JSON is a few hundred bytes).
MAX_BODY_BYTES = 16_384
NO_STORE = {"Cache-Control": "no-store, no-cache, must-revalidate, max-age=0", "Pragma": "no-cache"}


@dataclass
class StreamClient:
    """One connected MJPEG client."""

    id: int
    remote: str
    connected_ns: int = field(default_factory=time.monotonic_ns)
    sent: int = 0
    skipped: int = 0
    meter: RateMeter = field(default_factory=RateMeter)

    def summary(self) -> dict[str, Any]:
        return {"id": self.id, "remote": self.remote, "sent": self.sent, "skipped": self.skipped,
                "fps": round(self.meter.rate(), 2),
                "connected_s": round((time.monotonic_ns() - self.connected_ns) / 1e9, 1)}


class StreamHub:
    """The newest preview JPEG on the event loop, and the clients waiting for it."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self.latest: EncodedFrame | None = None
        self._event = asyncio.Event()
        self.clients: dict[int, StreamClient] = {}
        self._ids = itertools.count(1)
        self.streamed = RateMeter()
        self._max_sent_seq = 0
        self.sent_latency = LatencyWindow()

    def on_frame(self, item: EncodedFrame) -> None:
        """Called from the encoder thread."""
        try:
            self._loop.call_soon_threadsafe(self._publish, item)
        except RuntimeError:  # the loop is closed: the server is shutting down
            pass

    def _publish(self, item: EncodedFrame) -> None:
        self.latest = item
        event, self._event = self._event, asyncio.Event()
        event.set()

    async def wait_newer(self, seq: int, timeout: float) -> EncodedFrame | None:
        """The newest JPEG if its seq is above ``seq``, waiting up to ``timeout`` s for one; else None."""
        item = self.latest
        if item is not None and item.seq > seq:
            return item
        try:
            await asyncio.wait_for(self._event.wait(), timeout)
        except TimeoutError:
            return None
        item = self.latest
        return item if item is not None and item.seq > seq else None

    def register(self, remote: str) -> StreamClient:
        client = StreamClient(next(self._ids), remote)
        self.clients[client.id] = client
        return client

    def sent(self, client: StreamClient, item: EncodedFrame, previous_seq: int) -> None:
        now = time.monotonic_ns()
        client.sent += 1
        if previous_seq:
            client.skipped += item.seq - previous_seq - 1
        client.meter.tick(now)
        if item.seq > self._max_sent_seq:
            self._max_sent_seq = item.seq
            self.streamed.tick(now)
        if item.signal:
            self.sent_latency.add((now - item.host_time_ns) / 1e6)


def part_bytes(item: EncodedFrame) -> bytes:
    """One multipart part: boundary, headers (type, length, timestamp, frame id), the JPEG, CRLF."""
    headers = [f"--{BOUNDARY}", "Content-Type: image/jpeg", f"Content-Length: {len(item.jpeg)}",
               f"X-Timestamp: {item.wall_time:.6f}", f"X-Signal: {'live' if item.signal else 'none'}"]
    if item.frame_id is not None:
        headers.append(f"X-Frame-Id: {item.frame_id}")
    return ("\r\n".join(headers) + "\r\n\r\n").encode() + item.jpeg + b"\r\n"


class TokenGuard:
    """ASGI middleware: bearer token on every path but /healthz, and a bound on request bodies.

    The token comes from ``Authorization: Bearer TOKEN`` or ``?token=TOKEN`` (for
    ``<img>`` tags, which cannot send headers). A wrong or missing token gets a
    bare 401.
    """

    def __init__(self, app: Any, token: str | None) -> None:
        self.app = app
        self.token = token.encode() if token else None

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        headers = dict(scope.get("headers") or [])
        length = headers.get(b"content-length")
        if length is not None and (not length.isdigit() or int(length) > MAX_BODY_BYTES):
            return await plain(send, 413, b"request body too large\n")
        if self.token is not None and scope.get("path") != "/healthz" and not self._authorised(scope, headers):
            return await plain(send, 401, b"unauthorized\n", [(b"www-authenticate", b'Bearer realm="svelive"')])
        return await self.app(scope, receive, send)

    def _authorised(self, scope: dict, headers: dict[bytes, bytes]) -> bool:
        given = b""
        auth = headers.get(b"authorization", b"")
        if auth[:7].lower() == b"bearer ":
            given = auth[7:].strip()
        elif scope.get("query_string"):
            values = parse_qs(scope["query_string"].decode("latin-1")).get("token", [])
            given = values[0].encode("latin-1", "replace") if values else b""
        return 0 < len(given) <= MAX_TOKEN_LENGTH and hmac.compare_digest(given, self.token)


async def plain(send: Any, status: int, body: bytes, extra: list[tuple[bytes, bytes]] | None = None) -> None:
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"text/plain; charset=utf-8"),
                            (b"content-length", str(len(body)).encode()), *(extra or [])]})
    await send({"type": "http.response.body", "body": body})


class ToneUpdate(BaseModel):
    model_config = ConfigDict(extra="forbid")
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

    model_config = ConfigDict(extra="forbid")
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


class CalibrateRequest(BaseModel):
    """Body of POST /api/calibrate/response (optional)."""

    model_config = ConfigDict(extra="forbid")
    max_degree: int = Field(6, ge=1, le=10)
    apply: bool = False


def process_stats() -> dict[str, float]:
    """Resident memory (MB) and CPU time (s) of this process."""
    with open("/proc/self/statm") as f:
        rss_pages = int(f.read().split()[1])
    times = os.times()
    return {"rss_mb": round(rss_pages * os.sysconf("SC_PAGE_SIZE") / 2**20, 1),
            "cpu_s": round(times.user + times.system, 2)}


def listen_socket(settings: ServerSettings) -> socket.socket:
    """The bound, listening server socket; accepted client sockets inherit its send buffer size.

    A bounded send buffer keeps a slow client's backlog in the kernel small, so
    it skips to the newest frame instead of watching old video.
    """
    family = socket.AF_INET6 if ":" in settings.host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        if settings.send_buffer_kb:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, settings.send_buffer_kb * 1024)
        sock.bind((settings.host, settings.port))
        sock.listen(128)
    except OSError as exc:
        sock.close()
        raise SveliveError(f"cannot listen on {settings.host}:{settings.port}: {exc.strerror or exc}") from None
    return sock


def validation_message(exc: RequestValidationError) -> str:
    """One line for a rejected request: where the first problem is and what it is."""
    errors = exc.errors()
    if not errors:
        return "invalid request"
    first = errors[0]
    where = ".".join(str(part) for part in first.get("loc", ()) if part != "body") or "body"
    more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
    return f"{where}: {first.get('msg', 'invalid')}{more}".replace("\n", " ")


def viewer_html() -> str:
    return (resources.files("service") / "static" / "index.html").read_text(encoding="utf-8")


def create_app(pipeline: Pipeline, settings: ServerSettings, *, manage_pipeline: bool = True) -> FastAPI:
    """The HTTP app over ``pipeline``; with ``manage_pipeline`` it starts and stops it with the server."""
    hub_ref: dict[str, StreamHub] = {}

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        hub = StreamHub(asyncio.get_running_loop())
        hub_ref["hub"] = hub
        app.state.hub = hub
        pipeline.add_listener(hub.on_frame)
        if manage_pipeline:
            await run_in_threadpool(pipeline.start)
        try:
            yield
        finally:
            pipeline.remove_listener(hub.on_frame)
            if manage_pipeline:
                await run_in_threadpool(pipeline.stop)

    app = FastAPI(title="svelive", lifespan=lifespan, docs_url=None, redoc_url=None, openapi_url=None)
    app.state.pipeline = pipeline
    page = viewer_html()

    @app.exception_handler(SveliveError)
    async def bad_value(request: Request, exc: SveliveError) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=422)

    @app.exception_handler(RequestValidationError)
    async def bad_request(request: Request, exc: RequestValidationError) -> JSONResponse:
        return JSONResponse({"detail": validation_message(exc)}, status_code=422)

    @app.exception_handler(CalibrationBusy)
    async def busy(request: Request, exc: CalibrationBusy) -> JSONResponse:
        return JSONResponse({"detail": str(exc)}, status_code=409)

    @app.get("/healthz")
    async def healthz() -> dict[str, Any]:
        return {"status": "ok", "source": "online" if pipeline.online() else "offline"}

    @app.get("/", response_class=HTMLResponse)
    async def viewer() -> HTMLResponse:
        return HTMLResponse(page, headers=NO_STORE)

    @app.get("/stream.mjpg")
    async def stream(request: Request, fps: float | None = Query(None, gt=0, le=120)) -> StreamingResponse:
        hub = hub_ref["hub"]
        min_interval = 0.0 if fps is None else 1.0 / fps
        remote = f"{request.client.host}:{request.client.port}" if request.client else "?"

        async def parts():
            client = hub.register(remote)
            pipeline.watch(+1)
            try:
                last = 0
                while True:
                    item = await hub.wait_newer(last, timeout=1.0)
                    if item is None:
                        if await request.is_disconnected():
                            return
                        continue
                    yield part_bytes(item)
                    hub.sent(client, item, last)
                    last = item.seq
                    if min_interval:
                        await asyncio.sleep(min_interval)
            finally:
                pipeline.watch(-1)
                hub.clients.pop(client.id, None)

        return StreamingResponse(parts(), media_type=f"multipart/x-mixed-replace; boundary={BOUNDARY}",
                                 headers={**NO_STORE, "X-Accel-Buffering": "no"})

    @app.get("/snapshot.jpg")
    async def snapshot_jpg() -> Response:
        item = await run_in_threadpool(pipeline.snapshot_jpeg, 2.0)
        if item is None:
            return JSONResponse({"detail": "no frame yet"}, status_code=503)
        return Response(item.jpeg, media_type="image/jpeg",
                        headers={**NO_STORE, "X-Timestamp": f"{item.wall_time:.6f}", "X-Frame-Id": str(item.frame_id)})

    @app.get("/snapshot.exr")
    async def snapshot_exr(half: bool = Query(False)) -> Response:
        published = pipeline.latest()  # one immutable record: never torn between two frames
        if published is None:
            return JSONResponse({"detail": "no frame yet"}, status_code=503)
        hdr = published.hdr
        attributes = {"frameId": int(hdr.frame_id), "timestamp": f"{published.wall_time:.6f}",
                      "pattern": str(published.camera.pattern), "method": hdr.method,
                      "blackLevel": float(published.camera.sensor.black_level),
                      "whiteLevel": float(published.camera.sensor.white_level),
                      "units": "radiance, DN at relative exposure 1"}

        def encode() -> bytes:  # colour conversion and compression off the event loop
            channels, colour = pipeline.exr_image(published)
            return exr_bytes(channels, {**attributes, **colour}, half=half)

        data = await run_in_threadpool(encode)
        return Response(data, media_type="image/x-exr",
                        headers={**NO_STORE, "X-Timestamp": f"{published.wall_time:.6f}",
                                 "X-Frame-Id": str(hdr.frame_id),
                                 "Content-Disposition": f'attachment; filename="svelive-{hdr.frame_id}.exr"'})

    @app.get("/api/state")
    async def state() -> dict[str, Any]:
        hub = hub_ref["hub"]
        out = await run_in_threadpool(pipeline.state)
        out["fps"]["streamed"] = round(hub.streamed.rate(), 2)
        out["latency_ms"]["arrival_to_sent"] = hub.sent_latency.summary()
        out["clients"] = len(hub.clients)
        out["client_list"] = [c.summary() for c in list(hub.clients.values())[:100]]
        out["drops"]["client_skipped"] = sum(c.skipped for c in hub.clients.values())
        out["server"] = {"tasks": len(asyncio.all_tasks()), "host": settings.host, "port": settings.port,
                         "auth": settings.token is not None, **process_stats()}
        return out

    @app.get("/api/settings")
    async def get_settings() -> dict[str, Any]:
        return pipeline.settings()

    @app.put("/api/settings")
    async def put_settings(update: SettingsUpdate) -> dict[str, Any]:
        tone = update.tone.model_dump(exclude_none=True) if update.tone else None
        return pipeline.update_settings(method=update.method, jpeg_quality=update.jpeg_quality, tone=tone,
                                        colour=update.colour())

    @app.post("/api/calibrate/response")
    async def calibrate_response(request: CalibrateRequest | None = None) -> Any:
        # seconds of numpy at full HD: in a worker thread, so the streams keep flowing
        request = request or CalibrateRequest()
        data = await run_in_threadpool(pipeline.calibrate_response, request.max_degree, request.apply)
        if data is None:
            return JSONResponse({"detail": "no frame yet"}, status_code=503)
        return JSONResponse(data, headers=NO_STORE)

    @app.get("/api/calibrate/response")
    async def last_calibration() -> Any:
        data = pipeline.last_calibration()
        if data is None:
            return JSONResponse({"detail": "no calibration yet"}, status_code=404)
        return JSONResponse(data, headers=NO_STORE)

    @app.delete("/api/calibrate/response")
    async def reset_response() -> dict[str, Any]:
        return {"response": pipeline.reset_response()}

    app.add_middleware(TokenGuard, token=settings.token)
    if settings.cors_origins:  # outermost, so that it answers preflight requests (they carry no token)
        from fastapi.middleware.cors import CORSMiddleware

        app.add_middleware(CORSMiddleware, allow_origins=list(settings.cors_origins),
                           allow_methods=["GET", "PUT", "POST", "DELETE"], allow_headers=["Authorization", "Content-Type"])
    return app
