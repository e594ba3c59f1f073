"""The ``svelive serve`` verb: the live HDR service."""

from __future__ import annotations

import argparse
import ipaddress
import logging
import re
import sys
import threading
import time

from svelive.options import SOURCE_CFA_HELP, add_camera_option


def add_commands(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "serve", help="serve live HDR video over HTTP (MJPEG preview, EXR snapshots, state)",
        description="Reconstruct a live SVE source and serve it: viewer page at /, MJPEG at /stream.mjpg, "
                    "/snapshot.jpg, /snapshot.exr, /api/state, PUT /api/settings, POST /api/calibrate/response, /healthz. Every option can "
                    "also come from SVELIVE_<NAME> (e.g. SVELIVE_PORT) or a TOML/JSON config file; "
                    "precedence: command line > environment > config file > defaults.")
    # Defaults are None: "not given", so that the environment and the config file can fill them.
    p.add_argument("--config", metavar="PATH", help="TOML or JSON settings file (or SVELIVE_CONFIG)")
    p.add_argument("--source", help="source spec: demo (default), gige[:ID], v4l2:/dev/videoN, images:GLOB, replay:PATH")
    p.add_argument("--source-option", dest="source_options", action="append", metavar="KEY=VALUE",
                   help="source option, repeatable (e.g. fps=30, width=1920)")
    add_camera_option(p, "pattern", "exposure pattern, e.g. 1,4/16,64, or a colour layout such as dual-iso "
                                    "(default: the source's own)")
    add_camera_option(p, "cfa", SOURCE_CFA_HELP)
    add_camera_option(p, "black_level")
    add_camera_option(p, "white_level")
    p.add_argument("--method", help="reconstruction method (see `svelive methods`)")
    p.add_argument("--no-temporal", dest="temporal", action="store_const", const=False,
                   help="reconstruct every frame on its own (no temporal fusion)")
    p.add_argument("--live-quality", choices=("adaptive", "fixed"),
                   help="adaptive (default): while the machine cannot keep the camera's rate, step down to cheaper "
                        "live settings (weighted, no fusion) and back up with headroom; fixed: never")
    p.add_argument("--response", metavar="JSON",
                   help="response file (svelive calibrate response): linearise every frame before reconstruction")
    p.add_argument("--mask", metavar="NPZ",
                   help="mask file (svelive calibrate mask): the per-pixel exposure map of the sensor")
    p.add_argument("--workers", type=int, help="threads for the reconstruction (default 0: one per core)")
    p.add_argument("--parallel-frames", type=int, metavar="N",
                   help="frames reconstructed at once, the threads shared among them (default 1: each frame over "
                        "every thread, the lowest latency; 2: more frames per second at a higher latency)")
    p.add_argument("--refresh", type=int, metavar="K",
                   help="streams with fusion, monochrome and colour: run the method per frame only on the bands whose "
                        "history needs it and a round-robin 1/K of the settled ones (default 8; 0: every band every "
                        "frame)")
    p.add_argument("--host", help="address to bind (default 127.0.0.1)")
    p.add_argument("--port", type=int, help="TCP port (default 8000)")
    p.add_argument("--token", help="require Authorization: Bearer TOKEN (or ?token=) on every endpoint but /healthz; "
                                   "prefer --token-file or SVELIVE_TOKEN, which do not show in ps")
    p.add_argument("--token-file", metavar="PATH", help="read the token from the first line of this file")
    p.add_argument("--allowed-host", dest="allowed_hosts", action="append", metavar="NAME",
                   help="a host name clients reach this server by (the Host header), repeatable; the bound "
                        "address (and localhost on loopback) is always allowed")
    p.add_argument("--header-timeout-s", type=float,
                   help="close a connection whose request headers take longer than this (default 10)")
    p.add_argument("--max-connections", type=int, help="refuse connections beyond this many (default 512)")
    p.add_argument("--rtsp", dest="rtsp_port", type=int, metavar="PORT",
                   help="also serve the preview as H.264 over RTSP at rtsp://HOST:PORT/cam/NAME for every "
                        "camera, the first also at rtsp://HOST:PORT/live (default 0: off)")
    p.add_argument("--metrics-public", action="store_const", const=True,
                   help="serve /metrics (Prometheus) without the token")
    p.add_argument("--cors-origin", dest="cors_origins", action="append", metavar="ORIGIN",
                   help="allow this origin by CORS, repeatable (default: no CORS)")
    p.add_argument("--jpeg-quality", type=int, help="preview JPEG quality 10..100 (default 80)")
    p.add_argument("--preview-width", type=int, help="downscale previews wider than this (default 0: full size)")
    p.add_argument("--queue", type=int, help="capture hand-off depth in frames, 1..8 (default 1)")
    p.add_argument("--exposure-ev", type=float, help="preview exposure compensation in stops (default 0)")
    p.add_argument("--key", type=float, help="preview middle grey 0.01..0.9 (default 0.18)")
    p.add_argument("--white-percentile", type=float, help="radiance percentile shown as white (default 99.5)")
    p.add_argument("--adapt-s", type=float, help="preview adaptation time constant in s (default 0.2)")
    p.add_argument("--white-balance", metavar="auto|R,G,B",
                   help="colour cameras: 'auto' (default: estimated from the frames, smoothed over time) or fixed "
                        "multipliers R,G,B (normalised to G = 1), e.g. 2.0,1,1.5")
    p.add_argument("--colour-matrix", metavar="9 NUMBERS|none",
                   help="colour cameras: 3x3 matrix from white-balanced camera RGB to linear Rec.709, row-major, "
                        "comma-separated (default none)")
    p.add_argument("--output-space", choices=("camera", "rec709"),
                   help="what colour EXR snapshots hold: camera RGB as reconstructed (default) or Rec.709 "
                        "(white balance and --colour-matrix applied)")
    p.add_argument("--send-buffer-kb", type=int, help="kernel send buffer per client in KiB (default 256; 0: system)")
    p.add_argument("--log-level", help="uvicorn log level (default info)")
    p.set_defaults(func=cmd_serve)


def cmd_serve(args: argparse.Namespace) -> int:
    import uvicorn

    from svelive.exr import compress_on
    from svelive.memory import keep_freed_memory

    from service.app import create_app, listen_socket
    from service.protocol import bounded_protocol
    from service.pipeline import Pipeline
    from service.settings import resolve

    cli = {k: v for k, v in vars(args).items() if k not in ("func", "command", "config")}
    if cli["source_options"] is not None:
        cli["source_options"] = ",".join(cli["source_options"])
    settings = resolve(cli, config=args.config)
    server = settings.server
    configs = settings.named_pipelines()
    for config in configs.values():
        # build (not open) each source once, so a bad spec or option fails now with one line
        config.build_source()
    if server.token is None and not is_loopback(server.host):
        print(f"svelive serve: warning: listening on {server.host} without a token; anyone who can reach "
              "this address can watch", file=sys.stderr)
    # the configured response and mask files are read as each pipeline is built: a bad one fails now, in one line
    pipelines = {name: Pipeline(config) for name, config in configs.items()}
    # the ports next: a busy one is said at once, not after minutes of compiling
    sock = listen_socket(server)
    try:
        if server.rtsp_port:
            from service.publishers.rtsp import check_port

            check_port(server.host, server.rtsp_port)
    except BaseException:
        sock.close()
        raise
    keep_freed_memory()  # frame buffers reused, not page-faulted in anew every frame
    compress_on()  # EXR snapshots compressed on every core

    def say(line: str) -> None:
        print(f"svelive serve: {line}", file=sys.stderr, flush=True)

    # the kernels before the first live frame, while the HTTP server already answers ("warming up"); the app
    # starts the RTSP server (--rtsp) after them, then the pipelines
    app = create_app(pipelines, server, warm_up=lambda: warm_up_kernels("svelive serve"), say=say)
    shown = "127.0.0.1" if server.host in ("0.0.0.0", "::") else server.host
    for index, (name, config) in enumerate(configs.items()):
        paths = [f"http://{shown}:{server.port}/cam/{name}/"] + ([f"http://{shown}:{server.port}/"] if index == 0 else [])
        print(f"svelive serve: {config.source} on {' and '.join(reversed(paths))}", file=sys.stderr, flush=True)
    redact_tokens(logging.getLogger("uvicorn.access"))
    try:
        uvicorn.Server(uvicorn.Config(app, log_level=server.log_level, timeout_graceful_shutdown=2,
                                      access_log=server.log_level in ("debug", "trace"),
                                      http=bounded_protocol(server.header_timeout_s, server.max_connections),
                                      timeout_keep_alive=5)).run(sockets=[sock])
    finally:
        sock.close()
    return 0


class Ticker:
    """Says on stderr what a long step does: a line at the start, one every ``every_s`` seconds while it
    runs, and how long it took (a context manager; the lines come from a thread of its own)."""

    def __init__(self, prefix: str, doing: str, every_s: float = 15.0) -> None:
        self.prefix, self.doing, self.every_s = prefix, doing, every_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._tick, name="svelive-ticker", daemon=True)
        self._started = 0.0

    def say(self, text: str) -> None:
        print(f"{self.prefix}: {text}", file=sys.stderr, flush=True)

    def _tick(self) -> None:
        while not self._stop.wait(self.every_s):
            self.say(f"still {self.doing.split(' (')[0]}: {time.monotonic() - self._started:.0f} s")

    def __enter__(self) -> Ticker:
        self._started = time.monotonic()
        self.say(f"{self.doing}...")
        self._thread.start()
        return self

    def __exit__(self, kind: object, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        if kind is None:
            self.say(f"ready in {time.monotonic() - self._started:.0f} s")


def warm_up_kernels(prefix: str) -> None:
    """Compile every kernel the service runs (reconstruction and preview) into numba's disk cache in a child
    process, for this one to load as frames need them, saying so on stderr (a first start on a machine compiles
    for minutes).

    The compiling is left to the child because a process that compiles keeps LLVM's memory for the rest of its
    life (svelive.jit.compile_elsewhere); where no child can do it, this process compiles, and says so. Each kernel
    is loaded when a frame first needs it (about a second more for the first frame): loading every kernel here,
    the colour ones for a monochrome camera too, kept more (benchmarks/service.py, mono, loaded: 553 MB against
    504-515). After every load the libraries' pages are unmapped (svelive.jit.unmap_libraries_after_loads): LLVM's,
    which only the loads use, leave this process's resident memory."""
    from svelive.jit import compile_elsewhere, unmap_libraries_after_loads

    unmap_libraries_after_loads()
    with Ticker(prefix, "preparing the reconstruction kernels (loaded from numba's cache; a first start on this "
                        "machine compiles them, 1-5 minutes)") as ticker:
        why = compile_elsewhere(compile_service_kernels)
        if why is not None:
            ticker.say(f"{why}: compiling the kernels in this process instead, which keeps the compiler's memory")
            compile_service_kernels()


def compile_service_kernels() -> None:
    """Compile, or load from numba's disk cache, every kernel the service runs (reconstruction and preview) and
    the demo camera's render pass (the default source's, compiled when it opens)."""
    from svelive.capture import open_source
    from svelive.reconstruction.warmup import warm_up
    from svelive.tonemap import warm_up as warm_up_preview

    warm_up()
    warm_up_preview()
    open_source("demo").open().close()


class TokenRedactor(logging.Filter):
    """Replaces the value of ``token=`` in a log record's arguments (access logs show query strings)."""

    PATTERN = re.compile(r"(token=)[^&\s\"]*", re.IGNORECASE)

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.args, tuple):
            record.args = tuple(self.PATTERN.sub(r"\1***", a) if isinstance(a, str) else a for a in record.args)
        return True


def redact_tokens(logger: logging.Logger) -> None:
    """Keep tokens given as ``?token=`` out of ``logger``'s output."""
    logger.addFilter(TokenRedactor())


def is_loopback(host: str) -> bool:
    """True for localhost and loopback addresses."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False
