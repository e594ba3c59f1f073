"""The FastAPI app: one set of routers per served camera, the first also at the root paths.

Each camera's routes (viewer, MJPEG stream, snapshots, state, settings, calibration)
live in ``service/routers/``; the publishers they call (the MJPEG fan-out, the RTSP server,
snapshots, the state, metrics) in ``service/publishers/``; the token and the body bound in
``service/guard.py``. This module only assembles them and starts and stops the
pipelines and the publishers with the server (its lifespan).
"""

from __future__ import annotations

import asyncio
import logging
import signal
import socket
import threading
from collections.abc import Callable, Mapping
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.concurrency import run_in_threadpool

from service.guard import HostPolicy, SiteGuard, TokenGuard
from service.pipeline import CalibrationBusy, Pipeline
from service.publishers.mjpeg import StreamHub
from service.publishers.rtsp import RtspPublisher, RtspServer
from service.routers import ServedCamera, calibration, metrics, monitor, snapshots, state, stream
from service.routers import settings as settings_router
from service.settings import DEFAULT_CAMERA, ServerSettings
from svelive.core.errors import SveliveError

#: Longest wait for each pipeline thread at shutdown; a thread still inside a blocking camera call
#: (a GigE camera that vanished) is left behind (threads are daemons), so SIGTERM exits within 2.5 s.
STOP_JOIN_S = 0.75


def on_exit_signal(callback: Callable[[], None]) -> Callable[[], None]:
    """Call ``callback()`` first when SIGINT or SIGTERM arrives, then the handler in place (uvicorn's,
    which starts its graceful shutdown); returns a function that puts the handlers back.

    Installed only from the main thread (the only one Python delivers signals to); elsewhere
    nothing is installed. A handler that is not a Python function (default, ignore) is left alone.
    """
    if threading.current_thread() is not threading.main_thread():
        return lambda: None
    installed: dict[int, tuple[Any, Any]] = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        previous = signal.getsignal(sig)
        if not callable(previous):
            continue

        def chained(signum: int, frame: Any, previous: Any = previous) -> None:
            callback()
            previous(signum, frame)

        signal.signal(sig, chained)
        installed[sig] = (previous, chained)

    def restore() -> None:
        for sig, (previous, chained) in installed.items():
            if signal.getsignal(sig) is chained:
                signal.signal(sig, previous)

    return restore


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


def one_line(text: str, limit: int = 300) -> str:
    """``text`` as one printable line any JSON encoder takes: no line breaks, lone surrogates and
    other unencodable characters escaped, at most ``limit`` characters."""
    line = " ".join(str(text).split())
    line = line.encode("utf-8", "backslashreplace").decode("utf-8")
    return line if len(line) <= limit else line[:limit - 3] + "..."


def validation_message(exc: RequestValidationError) -> str:
    """One line for a rejected request: where the first problem is and what it is (never the input itself)."""
    errors = exc.errors()
    if not errors:
        return "invalid request"
    first = errors[0]
    if first.get("type") == "json_invalid":
        position = next((part for part in first.get("loc", ()) if isinstance(part, int)), None)
        reason = (first.get("ctx") or {}).get("error") or "JSON decode error"
        where = "" if position is None else f" at character {position}"
        return one_line(f"the body is not valid JSON{where}: {reason}")
    where = ".".join(str(part) for part in first.get("loc", ()) if part != "body") or "body"
    more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
    return one_line(f"{where}: {first.get('msg', 'invalid')}{more}")


class Startup:
    """Starts the cameras' pipelines with the server, after ``warm_up()`` when one is given: that in a thread of
    its own, so that the server answers at once (each pipeline's state ``warming_up``, /healthz not ready) while the
    kernels compile, minutes on a fresh machine. A warm-up that fails is logged and the pipelines start anyway (the
    kernels then compile at the first frame). Without ``manage`` the pipelines are left to the caller. The RTSP
    server (``rtsp``), if any, starts just before the pipelines, after the warm-up, so that its clients get frames at
    once, and of the frames' size; ``say`` is told each camera's RTSP URLs."""

    def __init__(self, cameras: list[ServedCamera], warm_up: Callable[[], None] | None, *, manage: bool = True,
                 rtsp: RtspServer | None = None, say: Callable[[str], None] | None = None) -> None:
        self.cameras = cameras
        self.managed = cameras if manage else []
        self.warm_up = warm_up
        self.rtsp = rtsp
        self.say = say or logging.getLogger("uvicorn.error").info
        self._lock = threading.Lock()
        self._closing = False
        self._started: list[ServedCamera] = []

    async def begin(self) -> None:
        """Start the pipelines now, or mark them warming up and start them after the warm-up."""
        if self.warm_up is None:
            await run_in_threadpool(self._start_rtsp)
            for cam in self.managed:
                await run_in_threadpool(self._start, cam)
            return
        for cam in self.managed:
            cam.pipeline.warming_up = True
        # a daemon: a stop during the warm-up does not wait for the compiler
        threading.Thread(target=self._warm_up_then_start, name="svelive-warm-up", daemon=True).start()

    def _warm_up_then_start(self) -> None:
        try:
            self.warm_up()
        except Exception as exc:  # noqa: BLE001 - said, and the service goes on without a warm-up
            logging.getLogger("uvicorn.error").warning("warm-up failed (%s); the pipelines start anyway",
                                                       one_line(exc))
        try:
            self._start_rtsp()
        except Exception as exc:  # noqa: BLE001 - said; HTTP goes on (the port was free when serve began)
            logging.getLogger("uvicorn.error").error("RTSP did not start (%s)", one_line(exc))
        for cam in self.managed:
            self._start(cam)

    def _start_rtsp(self) -> None:
        with self._lock:
            if self.rtsp is None or self._closing:
                return
            self.rtsp.start()
        for cam in self.cameras:
            if cam.rtsp is not None:
                urls = [self.rtsp.url(path) for path in reversed(cam.rtsp.paths)]
                self.say(f"{cam.name} as RTSP on {' and '.join(urls)}")

    def _start(self, cam: ServedCamera) -> None:
        with self._lock:
            if not self._closing:
                cam.pipeline.start()
                self._started.append(cam)

    def end(self) -> list[ServedCamera]:
        """No pipeline or RTSP server starts after this; returns the pipelines started."""
        with self._lock:
            self._closing = True
            return list(self._started)


def error(status: int, detail: object) -> JSONResponse:
    """A JSON error answer ``{"detail": "one line"}``."""
    return JSONResponse({"detail": one_line(str(detail))}, status_code=status)


def create_app(pipelines: Pipeline | Mapping[str, Pipeline], settings: ServerSettings, *,
               manage_pipeline: bool = True, warm_up: Callable[[], None] | None = None,
               say: Callable[[str], None] | None = None) -> FastAPI:
    """The HTTP app over one pipeline or named pipelines (in order: the first is also served at the root
    paths, every one at ``/cam/NAME/...``); with ``manage_pipeline`` it starts and stops them with the server,
    after ``warm_up()`` (the kernels), which runs while the server already answers (:class:`Startup`).

    With ``settings.rtsp_port`` every camera is also served over RTSP on that port (one :class:`RtspServer`:
    ``/cam/NAME``, the first camera also ``/live``), started after the warm-up and stopped with the server;
    ``say(line)`` is told the URLs (default: uvicorn's log)."""
    named = {DEFAULT_CAMERA: pipelines} if isinstance(pipelines, Pipeline) else dict(pipelines)
    if not named:
        raise SveliveError("no camera to serve")
    cameras = [ServedCamera(name, pipeline) for name, pipeline in named.items()]

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        loop = asyncio.get_running_loop()
        closing = asyncio.Event()
        app.state.closing = closing

        def shutdown_streams() -> None:  # from any thread or a signal handler
            loop.call_soon_threadsafe(closing.set)

        app.state.shutdown_streams = shutdown_streams
        # uvicorn waits for open responses before it shuts the app down: the endless MJPEG streams
        # must end as soon as the signal comes, not be cancelled (and logged as errors) later
        restore_signals = on_exit_signal(shutdown_streams)
        rtsp = None
        if settings.rtsp_port:
            # one port for every camera: /cam/NAME each, the first camera also at /live (the same encoding)
            rtsp = RtspServer(host=settings.host, port=settings.rtsp_port, token=settings.token)
        for index, cam in enumerate(cameras):
            cam.hub = StreamHub(cam.pipeline.jpeg_port)
            if rtsp is not None:
                cam.rtsp = RtspPublisher(cam.pipeline, server=rtsp, path=f"/cam/{cam.name}",
                                         aliases=("/live",) if index == 0 else ())
        app.state.hub = cameras[0].hub
        app.state.rtsp = rtsp
        startup = Startup(cameras, warm_up, manage=manage_pipeline, rtsp=rtsp, say=say)
        try:
            await startup.begin()
            yield
        finally:
            closing.set()
            started = startup.end()
            restore_signals()
            # stopped together, so that shutdown takes as long as the slowest camera, not their sum
            await asyncio.gather(*(run_in_threadpool(cam.pipeline.stop, STOP_JOIN_S) for cam in started),
                                 *([run_in_threadpool(rtsp.stop)] if rtsp is not None else []))

    app = FastAPI(title="svelive", lifespan=lifespan, docs_url=None, redoc_url=None, openapi_url=None)
    app.state.pipeline = cameras[0].pipeline
    app.state.cameras = cameras

    @app.exception_handler(SveliveError)
    async def bad_value(request: Request, exc: SveliveError) -> JSONResponse:
        return error(422, exc)

    @app.exception_handler(RequestValidationError)
    async def bad_request(request: Request, exc: RequestValidationError) -> JSONResponse:
        return error(422, validation_message(exc))

    @app.exception_handler(CalibrationBusy)
    async def busy(request: Request, exc: CalibrationBusy) -> JSONResponse:
        return error(409, exc)

    @app.get("/healthz")
    async def healthz() -> Any:
        cams = {cam.name: cam.pipeline.readiness() for cam in cameras}
        first = cams[cameras[0].name]
        # a readiness probe: not ready while any camera warms up or starts (Pipeline.readiness: a snapshot asked for
        # then would be refused); a camera that is offline does not hold the others back
        for waiting, status in (("warming_up", "warming up"), ("starting", "starting")):
            if waiting in cams.values():
                return JSONResponse({"status": status, "source": first, "cameras": cams}, status_code=503)
        return {"status": "ok", "source": first, "cameras": cams}

    app.include_router(metrics.router(cameras, settings))
    for index, cam in enumerate(cameras):
        routers = [stream.router(cam), snapshots.router(cam), state.router(cam, settings),
                   settings_router.router(cam), calibration.router(cam), monitor.router(cam)]
        for api in routers:
            app.include_router(api, prefix=f"/cam/{cam.name}")
            if index == 0:
                app.include_router(api)

    app.add_middleware(TokenGuard, token=settings.token,
                       public=("/healthz", "/metrics") if settings.metrics_public else ("/healthz",))
    if settings.cors_origins:  # outside the token, so that it answers preflight requests (they carry no token)
        from fastapi.middleware.cors import CORSMiddleware

        app.add_middleware(CORSMiddleware, allow_origins=list(settings.cors_origins),
                           allow_methods=["GET", "PUT", "POST", "DELETE"], allow_headers=["Authorization", "Content-Type"])
    # outermost: a request for another host name (DNS rebinding) or a cross-site write goes no further
    hosts = HostPolicy.for_server(settings.host, getattr(settings, "allowed_hosts", ()), settings.token is not None)
    app.add_middleware(SiteGuard, hosts=hosts, cors_origins=settings.cors_origins)
    return app
