"""Several cameras in one service: N demo cameras at WxH, one MJPEG client on each.

    python benchmarks/cameras.py [--cameras 2] [--size 1280x720] [--fps 30] [--seconds 60] [--cfa RGGB|none]

Starts ``svelive serve --config`` (a real server in a child process) with N demo
cameras, waits for every one to deliver, connects one MJPEG client per camera
(threads of this process, bodies read and dropped), and after ``--seconds``
prints per camera: captured / reconstructed / streamed fps, drops by cause,
reconstruction latency p50/p95, and for the process: CPU use (cores) and resident
memory. Progress goes to stderr every 10 s.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import socket
import subprocess
import sys
import tempfile
import threading
import time

import httpx


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def config_text(port: int, cameras: int, width: int, height: int, fps: float, cfa: str) -> str:
    lines = [f"port = {port}"]
    for i in range(cameras):
        lines += ["[[cameras]]", f'name = "cam{i}"', 'source = "demo"', f'cfa = "{cfa}"',
                  f"source_options = {{ width = {width}, height = {height}, fps = {fps} }}"]
        if cfa == "none":
            lines.append('pattern = "1,4/16,64"')
    return "\n".join(lines) + "\n"


def reader(url: str, stop: threading.Event, counts: dict, key: str) -> None:
    with httpx.Client(timeout=10) as client, client.stream("GET", url) as r:
        for chunk in r.iter_raw():
            counts[key] = counts.get(key, 0) + chunk.count(b"--svelive-frame")
            if stop.is_set():
                return


def cpu_seconds(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cameras", type=int, default=2)
    ap.add_argument("--size", default="1280x720")
    ap.add_argument("--fps", type=float, default=30.0)
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--cfa", default="RGGB", help="RGGB: the colour demo (dual-ISO Bayer); none: monochrome")
    args = ap.parse_args()
    width, height = (int(v) for v in args.size.lower().split("x"))
    port = free_port()
    with tempfile.TemporaryDirectory() as tmp:
        config = os.path.join(tmp, "cameras.toml")
        with open(config, "w") as f:
            f.write(config_text(port, args.cameras, width, height, args.fps, args.cfa))
        # run from this checkout's root: "-m" imports its svelive, not the one an editable install points at
        server = subprocess.Popen([sys.executable, "-m", "svelive.cli", "serve", "--config", config,
                                   "--log-level", "warning"], stderr=subprocess.DEVNULL,
                                  cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
        base = f"http://127.0.0.1:{port}"
        names = [f"cam{i}" for i in range(args.cameras)]
        try:
            deadline = time.monotonic() + 120
            while True:
                try:
                    states = [httpx.get(f"{base}/cam/{n}/api/state", timeout=2).json() for n in names]
                    if all(s["frames"]["reconstructed"] > 0 for s in states):
                        break
                except httpx.TransportError:
                    pass
                if server.poll() is not None or time.monotonic() > deadline:
                    raise SystemExit("svelive serve did not start")
                time.sleep(0.5)
            stop, counts = threading.Event(), {}
            threads = [threading.Thread(target=reader, args=(f"{base}/cam/{n}/stream.mjpg", stop, counts, n),
                                        daemon=True) for n in names]
            for t in threads:
                t.start()
            time.sleep(5)  # clients connected and encoders running before measuring
            cpu0, t0 = cpu_seconds(server.pid), time.monotonic()
            first = {n: httpx.get(f"{base}/cam/{n}/api/state", timeout=5).json() for n in names}
            while (elapsed := time.monotonic() - t0) < args.seconds:
                time.sleep(min(10.0, args.seconds - elapsed))
                print(f"  {time.monotonic() - t0:5.0f} s / {args.seconds:.0f} s", file=sys.stderr, flush=True)
            cpu = (cpu_seconds(server.pid) - cpu0) / (time.monotonic() - t0)
            last = {n: httpx.get(f"{base}/cam/{n}/api/state", timeout=5).json() for n in names}
            span = time.monotonic() - t0
            stop.set()
            result = {"machine": f"{platform.node()} {os.cpu_count()} cores", "cameras": args.cameras,
                      "size": args.size, "fps_target": args.fps, "cfa": args.cfa, "seconds": round(span, 1),
                      "cpu_cores": round(cpu, 2), "rss_mb": round(rss_mb(server.pid), 1), "per_camera": {}}
            for n in names:
                a, b = first[n], last[n]
                frames = {k: round((b["frames"][k] - a["frames"][k]) / span, 2)
                          for k in ("captured", "reconstructed", "encoded", "streamed")}
                result["per_camera"][n] = {"fps": frames,
                                           "drops": {k: v - a["drops"].get(k, 0) for k, v in b["drops"].items()},
                                           "reconstruct_ms": b["latency_ms"].get("reconstruct"),
                                           "method": b["method"]}
            print(json.dumps(result, indent=2))
        finally:
            server.terminate()
            try:
                server.wait(15)
            except subprocess.TimeoutExpired:
                server.kill()
    return 0


if __name__ == "__main__":
    sys.exit(main())
