"""The live service under load: replayed 1920x1200 12-bit frames at 30 fps, 10 MJPEG clients.

    python benchmarks/service.py [--minutes 10] [--clients 10] [--fps 30] [--idle-s 15] [--method weighted]
                                 [--no-temporal] [--workers N] [--scene pan|static] [--size 1920x1200]
                                 [--cfa none|RGGB]

Runs ``svelive serve``'s app (real uvicorn) in a child process over a source
that replays pre-rendered demo frames (1920x1200, 12-bit; ``--cfa none``, the
default: monochrome, pattern 1,4/16,64; ``--cfa RGGB``: the colour demo camera,
a Bayer mosaic with its dual-ISO exposures, labelled BayerRG12) at the target rate (``--scene pan``: the demo's camera pans, so every frame moves
and temporal fusion restarts each frame; ``static``: the same view, new noise in
every frame, so fusion runs on every pixel), then, from this process:

1. no client for ``--idle-s`` s: the server's CPU use (encoding is off when nobody watches);
2. ``--clients`` MJPEG clients for ``--minutes`` minutes: captured / reconstructed /
   streamed fps, drops by cause, latency from frame arrival to the part received by a
   client (X-Timestamp vs the receive time, same host clock) p50 / p95, the
   server's own arrival-to-sent latency, and its resident memory every 10 s (growth
   from the end of the first minute to the end).

The clients run in this process (asyncio, headers parsed, bodies skipped) and
so share the machine's cores with the server; on a real deployment they are
elsewhere.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import socket
import subprocess
import sys
import time
import urllib.request

import numpy as np

# Run as a script, this file's directory comes first on sys.path and its own name
# would hide the ``service`` package.
_HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or ".") != _HERE]


def replay_source_factory(fps: float, width: int, height: int, n: int = 24, static: bool = False,
                          cfa: str = "none"):
    """A factory of Sources replaying n pre-rendered demo frames at ``fps`` (fresh timestamps).

    ``static``: the demo's pan is stopped (a still view, independent noise in every frame).
    ``cfa``: ``"none"`` for the monochrome demo, else the colour filter of the colour demo.
    """
    from svelive.capture import Source
    from svelive.capture.demo import DemoSource
    from svelive.frame import Frame

    demo = DemoSource("demo", width=width, height=height, fps=0, period_s=1e9 if static else n / fps * 4, cfa=cfa)
    rendered = list(demo.frames(limit=n))
    demo.close()
    raws, label, camera = [f.raw for f in rendered], rendered[0].pixel_format, rendered[0].camera

    class Replay(Source):
        poll_s = 0.05

        def __init__(self) -> None:
            super().__init__("bench-replay")
            self.camera = camera
            self._n = 0
            self._t0 = 0.0

        def _open(self) -> None:
            self._t0 = time.monotonic()

        def _next(self):
            due = self._t0 + self._n / fps
            if not self._wait(min(due - time.monotonic(), self.poll_s)) or time.monotonic() < due:
                return None
            if time.monotonic() - due > 1.0:  # far behind: restart the clock rather than burst
                self._t0 = time.monotonic() - self._n / fps
            raw = raws[self._n % n]
            frame = Frame(raw=raw, frame_id=self._n, host_time_ns=time.monotonic_ns(), pixel_format=label,
                          camera=self.camera)
            self._n += 1
            return frame

    return Replay


def serve(port: int, fps: float, method: str | None, temporal: bool, workers: int, static: bool,
          size: tuple[int, int], cfa: str) -> None:
    """Child process: the service over the replay source."""
    import uvicorn

    from service.app import create_app, listen_socket
    from service.pipeline import Pipeline, PipelineConfig
    from service.settings import ServerSettings

    factory = replay_source_factory(fps, size[0], size[1], static=static, cfa=cfa)
    pipeline = Pipeline(PipelineConfig(source="bench-replay", method=method, temporal=temporal, workers=workers), factory)
    settings = ServerSettings(port=port, log_level="warning")
    sock = listen_socket(settings)
    print("ready", flush=True)
    uvicorn.Server(uvicorn.Config(create_app(pipeline, settings), log_level="warning",
                                  timeout_graceful_shutdown=1)).run(sockets=[sock])


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def get_state(port: int) -> dict:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/state", timeout=10) as r:
        return json.load(r)


def cpu_seconds(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


async def client(port: int, latencies: list[float], counts: list[int], index: int, stop: asyncio.Event) -> None:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(b"GET /stream.mjpg HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
    await writer.drain()
    await reader.readuntil(b"\r\n\r\n")  # response headers
    try:
        while not stop.is_set():
            head = await reader.readuntil(b"\r\n\r\n")
            received = time.time()
            headers = dict(line.split(": ", 1) for line in head.decode().split("\r\n")[1:] if ": " in line)
            await reader.readexactly(int(headers["Content-Length"]) + 2)
            if headers.get("X-Signal") == "live":
                latencies.append((received - float(headers["X-Timestamp"])) * 1e3)
                counts[index] += 1
    finally:
        writer.close()


async def load_phase(port: int, pid: int, n_clients: int, seconds: float) -> dict:
    latencies: list[float] = []
    counts = [0] * n_clients
    stop = asyncio.Event()
    tasks = [asyncio.create_task(client(port, latencies, counts, i, stop)) for i in range(n_clients)]
    rss: list[tuple[float, float]] = []
    t0 = time.monotonic()
    await asyncio.sleep(5)  # warm-up
    start_state, start_cpu, start_t = get_state(port), cpu_seconds(pid), time.monotonic()
    latencies.clear()
    while time.monotonic() - t0 < seconds:
        await asyncio.sleep(10)
        rss.append((time.monotonic() - t0, get_state(port)["server"]["rss_mb"]))
    end_state, end_cpu, end_t = get_state(port), cpu_seconds(pid), time.monotonic()
    stop.set()
    for task in tasks:
        task.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
    span = end_t - start_t
    frames = {k: (end_state["frames"][k] - start_state["frames"][k]) / span
              for k in ("captured", "reconstructed", "encoded")}
    first_minute = [m for t, m in rss if t <= 60] or [rss[0][1]]
    return {
        "fps_mean": {k: round(v, 2) for k, v in frames.items()},
        "fps_per_client_mean": round(float(np.mean(counts)) / (end_t - t0), 2),
        "latency_client_ms": {"p50": round(float(np.percentile(latencies, 50)), 1),
                              "p95": round(float(np.percentile(latencies, 95)), 1), "n": len(latencies)},
        "latency_server_ms": end_state["latency_ms"],
        "drops": end_state["drops"],
        "cpu_percent": round(100 * (end_cpu - start_cpu) / span, 1),
        "rss_mb": {"after_first_minute": first_minute[-1], "end": rss[-1][1],
                   "growth_percent": round(100 * (rss[-1][1] - first_minute[-1]) / first_minute[-1], 2),
                   "samples": rss},
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--clients", type=int, default=10)
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--idle-s", type=float, default=15.0)
    parser.add_argument("--method", default=None)
    parser.add_argument("--no-temporal", action="store_true", help="single-frame reconstruction (no fusion)")
    parser.add_argument("--workers", type=int, default=0, help="reconstruction threads per frame (0: one per core)")
    parser.add_argument("--scene", choices=("pan", "static"), default="pan",
                        help="pan: the whole view moves every frame; static: a still view (default pan)")
    parser.add_argument("--size", default="1920x1200", help="frame size WxH (default 1920x1200)")
    parser.add_argument("--cfa", default="none",
                        help="none: the monochrome demo frames (default); RGGB (or another layout): the colour demo")
    parser.add_argument("--serve-port", type=int, help=argparse.SUPPRESS)
    args = parser.parse_args()
    size = tuple(int(v) for v in args.size.lower().split("x"))
    if args.serve_port:
        serve(args.serve_port, args.fps, args.method, not args.no_temporal, args.workers, args.scene == "static", size,
              args.cfa)
        return
    port = free_port()
    cmd = [sys.executable, __file__, "--serve-port", str(port), "--fps", str(args.fps), "--workers", str(args.workers),
           "--scene", args.scene, "--size", args.size, "--cfa", args.cfa]
    if args.method:
        cmd += ["--method", args.method]
    if args.no_temporal:
        cmd.append("--no-temporal")
    child = subprocess.Popen(cmd, stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "ready"
        deadline = time.monotonic() + 60
        while True:
            try:
                if get_state(port)["frames"]["reconstructed"] > 10:
                    break
            except OSError:
                pass
            if time.monotonic() > deadline:
                raise SystemExit("the service did not start")
            time.sleep(0.5)
        time.sleep(2)
        c0, s0 = cpu_seconds(child.pid), get_state(port)
        time.sleep(args.idle_s)
        c1, s1 = cpu_seconds(child.pid), get_state(port)
        idle = {"cpu_percent": round(100 * (c1 - c0) / args.idle_s, 1),
                "fps": s1["fps"], "encoded_frames": s1["frames"]["encoded"] - s0["frames"]["encoded"]}
        load = asyncio.run(load_phase(port, child.pid, args.clients, args.minutes * 60))
    finally:
        child.terminate()
        child.wait(15)
    print(f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores; {args.size} 12-bit "
          f"{'monochrome' if args.cfa == 'none' else args.cfa + ' colour'} replay at "
          f"{args.fps:g} fps, method {args.method or 'default'}{' single-frame' if args.no_temporal else ' + temporal'}, workers {args.workers or os.cpu_count()}, {args.scene} scene, "
          f"{args.clients} clients, {args.minutes:g} min")
    print(f"no client: server CPU {idle['cpu_percent']} % of one core, {idle['encoded_frames']} frames encoded, "
          f"fps {idle['fps']}")
    print(f"{args.clients} clients: fps captured {load['fps_mean']['captured']}, reconstructed "
          f"{load['fps_mean']['reconstructed']}, encoded/streamed {load['fps_mean']['encoded']}, per client "
          f"{load['fps_per_client_mean']}; server CPU {load['cpu_percent']} %")
    print(f"latency arrival -> part received by a client: p50 {load['latency_client_ms']['p50']} ms, "
          f"p95 {load['latency_client_ms']['p95']} ms (n={load['latency_client_ms']['n']})")
    print(f"server stages: {json.dumps(load['latency_server_ms'])}")
    print(f"drops: {json.dumps(load['drops'])}")
    print("RSS samples (s, MB): " + ", ".join(f"{t:.0f}: {m}" for t, m in load["rss_mb"]["samples"][5::6]))
    print(f"RSS after first minute {load['rss_mb']['after_first_minute']} MB, at end {load['rss_mb']['end']} MB, "
          f"growth {load['rss_mb']['growth_percent']} %")


if __name__ == "__main__":
    main()
