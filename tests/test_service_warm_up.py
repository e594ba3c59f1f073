"""Issue 28.2: the viewer is served during the kernel warm-up. A real ``svelive serve`` (subprocess, loopback
port, the kernels loaded from numba's cache as on any start after the first, which takes seconds): from its first
answer /api/state says ``warming_up`` (source state ``warming_up``, no frame) and /healthz answers 503 (a readiness
probe: not ready), until the warm-up is done and frames come; the viewer page in headless Chromium shows
"warming up…" meanwhile, then "online". Before: the port was bound, but nothing answered until the warm-up was over
(minutes on a fresh machine)."""

from __future__ import annotations

import subprocess
import sys
import threading
import time

import httpx
import pytest

from tests.test_service_helpers import free_port, stop_process
from tests.test_viewer import browser_page, playwright_api


def poll(url: str, seen: list[tuple[float, bool, str, int, int]], stop: threading.Event) -> None:
    """Append (time, warming_up, source state, frames reconstructed, /healthz status) every 50 ms until ``stop``."""
    while not stop.is_set():
        try:
            state = httpx.get(url + "/api/state", timeout=5).json()
            health = httpx.get(url + "/healthz", timeout=5)
            seen.append((time.monotonic(), state["warming_up"], state["source"]["state"],
                         state["frames"]["reconstructed"], health.status_code))
        except httpx.TransportError:
            pass  # not listening yet
        stop.wait(0.05)


def test_serve_answers_while_it_warms_up_and_the_viewer_says_so(tmp_path):
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    with browser_page(tmp_path, 600, 15_000) as page:  # launched first: the warm-up takes only seconds
        proc = subprocess.Popen(
            [sys.executable, "-m", "svelive.cli", "serve", "--source", "demo", "--cfa", "none",
             "--source-option", "width=160", "--source-option", "height=96", "--port", str(port)],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        seen: list[tuple[float, bool, str, int, int]] = []
        stop = threading.Event()
        poller = threading.Thread(target=poll, args=(url, seen, stop), daemon=True)
        poller.start()
        try:
            deadline = time.monotonic() + 60
            while True:  # the page as soon as the port answers
                assert proc.poll() is None, f"serve exited: {proc.stderr.read()}"
                try:
                    page.goto(url + "/", wait_until="domcontentloaded")  # "load" waits for the first frame
                    break
                except playwright_api.Error:
                    assert time.monotonic() < deadline, "the viewer was not served within 60 s"
                    time.sleep(0.1)
            try:
                page.wait_for_function("document.getElementById('status').textContent === 'warming up…'",
                                       timeout=5_000)
            except playwright_api.Error:
                raise AssertionError(f"the viewer showed {page.text_content('#status')!r}; states {seen[:3]}, "
                                     f"{seen[-3:]}") from None
            page.wait_for_function("document.getElementById('status').textContent === 'online'", timeout=300_000)
            page.wait_for_function("/^\\d+/.test(document.getElementById('frame').textContent)")
            # the poller samples every 50 ms: let it see the frames the viewer already shows before it stops
            settled = time.monotonic() + 10
            while not (seen and seen[-1][3] > 0) and time.monotonic() < settled:
                time.sleep(0.05)
        finally:
            stop.set()
            poller.join(10)
            stop_process(proc)
    assert seen, "no state answered"
    first = seen[0]
    assert first[1:4] == (True, "warming_up", 0) and first[4] == 503, f"the first answer: {first}"
    warming = [s for s in seen if s[1]]
    assert all(s[2] == "warming_up" and s[3] == 0 for s in warming), warming
    # /healthz is asked just after the state: at the end of the warm-up it may already be ready
    assert all(s[4] == 503 for s in warming[:-1]), warming
    assert seen.index(warming[-1]) == len(warming) - 1, "warming up again after it was over"
    ready = seen[len(warming):]
    assert ready and ready[-1][3] > 0 and ready[-1][4] == 200, f"never ready: {seen[-3:]}"
    print(f"warming up for {ready[0][0] - first[0]:.1f} s after the first answer ({len(warming)} answers)")


if __name__ == "__main__":
    sys.exit(pytest.main([__file__, "-q", "-s"]))
