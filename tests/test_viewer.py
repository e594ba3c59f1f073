"""The viewer page in a real headless Chromium (Debian's /usr/bin/chromium through Playwright)."""

from __future__ import annotations

import os
import time
from contextlib import contextmanager
from pathlib import Path

import httpx
import numpy as np
import pytest

from tests.test_service_helpers import Camera, ServerThread, chart_raws, make_camera

CHROMIUM = os.environ.get("SVELIVE_CHROMIUM", "/usr/bin/chromium")
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync"]

playwright_api = pytest.importorskip("playwright.sync_api", reason="pip install playwright (uses /usr/bin/chromium)")
if not Path(CHROMIUM).exists():
    pytest.skip(f"no Chromium at {CHROMIUM} (apt-get install chromium)", allow_module_level=True)


@contextmanager
def browser_page(tmp_path: Path, height: int, timeout_ms: int, flags: tuple[str, ...] = ()):
    """A page of a fresh headless Chromium (viewport 900 x ``height``; more command-line ``flags``), closed
    afterwards."""
    with playwright_api.sync_playwright() as pw:
        context = pw.chromium.launch_persistent_context(
            str(tmp_path / "profile"), executable_path=CHROMIUM, headless=True, args=[*FLAGS, *flags],
            viewport={"width": 900, "height": height})
        try:
            page = context.new_page()
            page.set_default_timeout(timeout_ms)
            yield page
        finally:
            context.close()


@pytest.mark.parametrize("token", [None, "view-token"])
def test_viewer_loads_shows_live_video_and_state(tmp_path, token):
    camera = make_camera(fps=15.0)
    with ServerThread(camera, token=token) as srv, browser_page(tmp_path, 600, 15_000) as page:
        page.goto(srv.url + "/" + (f"?token={token}" if token else ""))
        page.wait_for_function("document.getElementById('live').naturalWidth > 0")
        assert page.evaluate("document.getElementById('live').naturalWidth") == 224
        page.wait_for_function("document.getElementById('status').textContent === 'online'")
        page.wait_for_function("/^\\d+/.test(document.getElementById('frame').textContent)")
        first_id = int(page.text_content("#frame").split()[0])
        first = page.locator("#live").screenshot()
        page.wait_for_function(f"parseInt(document.getElementById('frame').textContent) > {first_id + 5}")
        deadline = time.monotonic() + 10
        while page.locator("#live").screenshot() == first:  # the <img> really shows new frames
            assert time.monotonic() < deadline, "the live image never changed"
            time.sleep(0.2)
        assert "weighted" in page.eval_on_selector("#method", "s => [...s.options].map(o => o.value).join()")
        # the live-quality step that runs, as the state says it
        live = srv.pipeline.state()["live_quality"]
        shown = page.text_content("#live-quality")
        assert shown.startswith(live["name"]) and live["mode"] in shown
        # a control round trip: the exposure slider PUTs the setting
        page.eval_on_selector("#ev", "e => { e.value = '2'; e.dispatchEvent(new Event('change')); }")
        deadline = time.monotonic() + 5
        while srv.pipeline.settings()["tone"]["exposure_ev"] != 2.0:
            assert time.monotonic() < deadline, "the exposure control did not reach the server"
            time.sleep(0.1)
        # and the JPEG quality slider (its id once clashed with the live-quality row's)
        page.eval_on_selector("#quality", "e => { e.value = '55'; e.dispatchEvent(new Event('change')); }")
        deadline = time.monotonic() + 5
        while srv.pipeline.settings()["jpeg_quality"] != 55:
            assert time.monotonic() < deadline, "the JPEG quality control did not reach the server"
            time.sleep(0.1)
        shot = tmp_path / "viewer.png"
        page.screenshot(path=str(shot))
        assert shot.stat().st_size > 10_000
        if os.environ.get("SVELIVE_VIEWER_SCREENSHOT"):
            page.screenshot(path=os.environ["SVELIVE_VIEWER_SCREENSHOT"])


def test_viewer_calibrates_the_response_and_plots_the_curve(tmp_path):
    camera = Camera(fps=10.0, raws=chart_raws("gamma2.2"))
    with ServerThread(camera) as srv, browser_page(tmp_path, 700, 60_000) as page:
        page.goto(srv.url + "/")
        page.wait_for_function("document.getElementById('status').textContent === 'online'")
        assert page.get_attribute("#curve-path", "d") == ""
        page.check("#cal-apply")
        page.click("#calibrate")
        page.wait_for_function("document.getElementById('curve-path').getAttribute('d').length > 0")
        info = page.text_content("#cal-info")
        assert "degree" in info and "applied" in info, info
        # 65 points of the curve, inside the plot; it bows below the diagonal, as gamma 2.2's inverse does
        points = [tuple(map(float, p.split(","))) for p in
                  page.get_attribute("#curve-path", "d")[1:].split(" L")]
        assert len(points) == 65
        middle = points[32]  # M = 0.5: I = 0.5^2.2 = 0.22, i.e. y = 160 - 150 * 0.22
        assert abs(middle[1] - (160 - 150 * 0.5 ** 2.2)) < 150 * 0.02, middle
        page.wait_for_function("document.getElementById('response').textContent.includes('calibrated live')")
        assert srv.pipeline.response_state()["origin"] == "calibrated live"
        shot = tmp_path / "calibration.png"
        page.screenshot(path=str(shot))
        assert shot.stat().st_size > 10_000


def test_viewer_shows_a_colour_preview_and_the_white_balance(tmp_path):
    from tests.test_service_colour import ColourServer, make_colour_camera

    with ColourServer(make_colour_camera(fps=10.0)) as srv, browser_page(tmp_path, 700, 60_000) as page:
        page.goto(srv.url + "/")
        page.wait_for_function("document.getElementById('live').naturalWidth > 0")
        page.wait_for_function("document.body.dataset.cfa === 'RGGB'")
        # the pixels the browser decoded, read back through a canvas: the three channels differ
        pixels = page.evaluate("""() => {
            const img = document.getElementById('live');
            const canvas = document.createElement('canvas');
            canvas.width = img.naturalWidth; canvas.height = img.naturalHeight;
            const ctx = canvas.getContext('2d');
            ctx.drawImage(img, 0, 0);
            return Array.from(ctx.getImageData(0, 0, canvas.width, canvas.height).data);
        }""")
        rgba = np.array(pixels, float).reshape(-1, 4)
        assert rgba[:, :3].mean() > 5
        assert np.abs(rgba[:, 0] - rgba[:, 2]).mean() > 3 and np.abs(rgba[:, 0] - rgba[:, 1]).mean() > 2
        assert not page.locator("#colour-controls").is_hidden()
        page.wait_for_function("document.getElementById('colour').textContent.includes('white balance auto')")
        # fixing the white balance from the page: the server gets three numbers, green 1
        page.select_option("#wb-mode", "fixed")
        deadline = time.monotonic() + 10
        while srv.pipeline.settings()["white_balance"] == "auto":
            assert time.monotonic() < deadline, "the white balance control did not reach the server"
            time.sleep(0.1)
        fixed = srv.pipeline.settings()["white_balance"]
        assert len(fixed) == 3 and fixed[1] == 1
        page.wait_for_function("document.getElementById('colour').textContent.includes('white balance fixed')")
        page.eval_on_selector("#wbr", "e => { e.value = '1'; e.dispatchEvent(new Event('change')); }")
        deadline = time.monotonic() + 10
        while srv.pipeline.settings()["white_balance"][0] != pytest.approx(2.0):
            assert time.monotonic() < deadline, "the red slider did not reach the server"
            time.sleep(0.1)
        if os.environ.get("SVELIVE_VIEWER_SCREENSHOT"):
            page.screenshot(path=os.environ["SVELIVE_VIEWER_SCREENSHOT"].replace(".png", "-colour.png"))


def test_viewer_runs_an_exposure_sweep_shows_its_progress_and_the_curve_with_its_band(tmp_path, monkeypatch):
    from tests.test_calibration_sweep import ExposureSource, server

    camera = Camera(fps=25.0, raws=[np.zeros((192, 224), np.uint16)])
    sources = []

    def factory():
        sources.append(ExposureSource(camera, exposure_us=8000.0))
        return sources[-1]

    with server(monkeypatch, factory) as srv, browser_page(tmp_path, 900, 180_000) as page:
        page.goto(srv.url + "/")
        page.wait_for_function("document.getElementById('status').textContent === 'online'")
        assert page.locator("#sweep-bar").is_hidden()
        # the sweep is offered around the camera's own exposure, which the state reports
        page.wait_for_function("document.getElementById('sweep-times').value === '8000, 12000'")
        assert srv.state()["source"]["exposure_time"] == 8000.0
        # every text the progress line shows, kept by the page as it changes
        page.evaluate("""() => { window.sweepTexts = [];
            new MutationObserver(() => window.sweepTexts.push(document.getElementById('sweep-state').textContent))
              .observe(document.getElementById('sweep-state'), { childList: true, characterData: true, subtree: true }); }""")
        # refused by the server: the reason is shown, nothing starts
        page.fill("#sweep-times", "5000, 5000")
        page.click("#sweep")
        page.wait_for_function("document.getElementById('sweep-state').textContent.includes('refused')")
        assert "differ" in page.text_content("#sweep-state") and srv.state()["calibration"] is None
        page.fill("#sweep-times", "10000; 15000 22500")  # commas, semicolons or spaces
        page.check("#cal-apply")
        page.click("#sweep")
        page.wait_for_function("document.getElementById('sweep-state').textContent.includes('done')")
        texts = page.evaluate("window.sweepTexts")
        assert any("fitting" in t for t in texts), texts  # the progress was shown while it ran
        assert "3 frames at 10000, 15000, 22500" in texts[-1] and "exposure back to 8000" in texts[-1], texts[-1]
        assert page.evaluate("[document.getElementById('sweep-bar').value, document.getElementById('sweep-bar').max]") \
            == [4, 4]
        assert not page.is_disabled("#sweep")
        assert sources[-1].changes == [10_000.0, 15_000.0, 22_500.0, 8_000.0]  # and back
        # the result: its curve (gamma 2.2's inverse bows below the diagonal) and its band, from the job's result
        page.wait_for_function("document.getElementById('cal-info').textContent.includes('3 frames (sweep')")
        info = page.text_content("#cal-info")
        assert "sweep 10000, 15000, 22500" in info and "band" in info and "applied" in info, info
        points = [tuple(map(float, p.split(","))) for p in page.get_attribute("#curve-path", "d")[1:].split(" L")]
        assert len(points) == 65 and abs(points[32][1] - (160 - 150 * 0.5 ** 2.2)) < 150 * 0.02, points[32]
        band = page.get_attribute("#curve-band", "d")
        assert band.startswith("M") and band.endswith("Z")
        edge = [tuple(map(float, p.split(","))) for p in band[1:-2].split(" L")]
        result = httpx.get(srv.url + "/api/calibrate/response", timeout=10).json()
        n = len(result["stats"]["band"]["brightness"])
        assert len(edge) == 2 * n
        upper, lower = edge[:n], edge[n:][::-1]
        assert all(u[1] <= l[1] for u, l in zip(upper, lower))  # +2 SE above -2 SE (SVG y grows downwards)
        lo, hi = result["stats"]["measured_range"]
        assert upper[0][0] == pytest.approx(30 + 220 * lo, abs=0.06) and upper[-1][0] == pytest.approx(30 + 220 * hi, abs=0.06)
        page.wait_for_function("document.getElementById('response').textContent.includes('calibrated live')")
        if os.environ.get("SVELIVE_VIEWER_SCREENSHOT"):
            page.screenshot(path=os.environ["SVELIVE_VIEWER_SCREENSHOT"].replace(".png", "-sweep.png"), full_page=True)
