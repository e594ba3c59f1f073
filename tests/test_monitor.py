"""HDR monitoring (issue 30): pixel read-out, log2 histogram, overlay map; the pure functions, a real server,
and the viewer in headless Chromium."""

from __future__ import annotations

import concurrent.futures
import time

import httpx
import numpy as np
import pytest

from svelive import monitor
from svelive.core.camera import Camera as CameraDescription
from svelive.core.pattern import Pattern
from svelive.exr import read_exr
from svelive.simulation import exposure_scale, load_sample_scene, simulate
from svelive.tonemap import ToneSettings
from tests.test_service_helpers import PATTERN, SENSOR, Camera, ServerThread, make_camera

SHAPE = (192, 224)
BLOCK = (slice(40, 80), slice(60, 120))  # rows, columns of the clipped block: 2400 pixels


def clipped_block_camera(n: int = 3) -> Camera:
    """A camera showing the desk scene with a block far above what the shortest exposure holds."""
    pattern = Pattern.parse(PATTERN)
    scene = np.maximum(load_sample_scene("desk"), 0)
    scene = np.ascontiguousarray(scene * exposure_scale(scene, pattern, SENSOR, stops_below_fill=1))[:SHAPE[0], :SHAPE[1]]
    scene = scene.astype(np.float32)
    scene[BLOCK] = 1e6
    rng = np.random.default_rng(3)
    return Camera(fps=15.0, raws=[simulate(scene, pattern, SENSOR, seed=rng).raw for _ in range(n)])


def pause(srv: ServerThread, camera: Camera) -> int:
    """Stop the camera and wait until the newest reconstructed frame stays; returns its frame id."""
    srv.wait_for(lambda s: s["frames"]["reconstructed"] >= 2, timeout=20)
    camera.paused = True
    last, deadline = None, time.monotonic() + 10
    while True:
        time.sleep(0.3)
        now = srv.pipeline.latest().hdr.frame_id
        if now == last:
            return now
        assert time.monotonic() < deadline
        last = now


# ----- the pure functions ------------------------------------------------------------------------

def test_levels_follow_the_camera():
    camera = CameraDescription.build(PATTERN, None, SENSOR)
    assert monitor.clip_level(camera) == pytest.approx(SENSOR.censor_level / 1.0)
    assert monitor.noise_floor(camera) == pytest.approx(np.sqrt(SENSOR.floor_variance) / 64.0)
    wide = CameraDescription.build("2,8/32,128", None, SENSOR)
    assert monitor.clip_level(wide) == pytest.approx(SENSOR.censor_level / 2.0)


def test_overlay_map_equals_numpy_reference_mono_and_colour():
    rng = np.random.default_rng(1)
    for shape in ((37, 53), (37, 53, 3)):
        image = (2.0 ** rng.uniform(-12, 14, shape)).astype(np.float32)
        image[0, :5] = 0
        motion = rng.random(shape[:2]) < 0.2
        matrix = None if len(shape) == 2 else np.float32([[1.2, -0.1, 0], [0, 1, 0], [0, 0.1, 0.8]])
        grey, clip = 37.0, 4000.0
        got = monitor.overlay_map(image, grey, clip, motion, matrix)
        lum = monitor.luminance(image, matrix)
        s = monitor.stops(lum, grey)
        edges = [stop for stop, _ in monitor.FALSE_COLOUR[1:]]
        band = np.where(lum > 0, 1 + np.searchsorted(edges, s, side="right"), 0)
        near_edge = np.min(np.abs(s[..., None] - np.array(edges)), axis=-1) < 0.01  # the table's 0.4 % bins
        assert np.array_equal((got & 15)[~near_edge], band[~near_edge])
        assert np.array_equal((got & 16) > 0, monitor.brightest(image) >= clip)
        assert np.array_equal((got & 32) > 0, motion)
        assert not (got >> monitor.CONFIDENCE_SHIFT).any()  # no confidence given: level 0
        confidence = rng.random(shape[:2]).astype(np.float32)
        confidence[0, :3] = [0.5, 0.9, 0.99]  # exactly at the levels' bounds: the level above
        levels = monitor.overlay_map(image, grey, clip, motion, matrix, confidence) >> monitor.CONFIDENCE_SHIFT
        bounds = np.float32([1 / 2, 9 / 10, 99 / 100])  # c = SNR / (1 + SNR) at SNR 1, 9, 99, in float32
        expected = (confidence[..., None] >= bounds).sum(axis=-1)
        snr = confidence.astype(np.float64) / (1 - confidence.astype(np.float64))
        away = np.min(np.abs(np.log(snr[..., None] / [1.0, 9.0, 99.0])), axis=-1) > 1e-4
        assert np.array_equal(levels, expected) and set(np.unique(levels)) == {0, 1, 2, 3}
        assert np.array_equal(levels[away], np.searchsorted([1.0, 9.0, 99.0], snr[away], side="right"))
        assert levels[0, :3].tolist() == [1, 2, 3]


def test_histogram_counts_every_pixel_and_samples_large_frames():
    rng = np.random.default_rng(2)
    image = (2.0 ** rng.uniform(-8, 13, (100, 120))).astype(np.float32)
    image[:10] = 0
    h = monitor.histogram(image, clip=4000.0, floor=0.05)
    assert h.stride == 1 and h.pixels == image.size
    assert h.counts["Y"].sum() + h.zero["Y"] == image.size and h.zero["Y"] == 1200
    assert h.clipped == pytest.approx(np.mean(image >= 4000.0))
    assert h.below_noise_floor == pytest.approx(np.mean(image < 0.05))
    big = np.ones((1200, 1920, 3), np.float32)
    hb = monitor.histogram(big, clip=4000.0, floor=0.05)
    assert hb.stride == 3 and hb.pixels == 400 * 640 <= monitor.MAX_SAMPLES
    assert all(hb.counts[c].sum() == hb.pixels for c in "RGB")


def test_mid_grey_is_what_the_tone_mapper_maps_to_its_key():
    from svelive.tonemap import ToneMapper, curve_constants

    rng = np.random.default_rng(4)
    image = (2.0 ** rng.uniform(0, 10, (64, 64))).astype(np.float32)
    tone = ToneSettings(exposure_ev=1.5, adapt_s=0)
    mapper = ToneMapper(tone)
    mapper.update(image, 0)
    scale, _ = curve_constants(mapper.stats, tone)
    assert float(scale) * monitor.mid_grey(image, tone) == pytest.approx(tone.key, rel=1e-5)


# ----- a real server ---------------------------------------------------------------------------

def test_pixel_equals_the_exr_snapshot_mono_and_histogram_sees_the_clipped_block(monkeypatch):
    calls = []
    original = monitor.histogram
    monkeypatch.setattr(monitor, "histogram", lambda *a, **k: calls.append(1) or original(*a, **k))
    camera = clipped_block_camera()
    with ServerThread(camera) as srv:
        srv.wait_for(lambda s: s["frames"]["reconstructed"] >= 3, timeout=20)
        assert calls == []  # nobody asked: nothing computed
        assert "_made_confidence" not in srv.pipeline.latest().hdr.__dict__  # nor the confidence map
        frame_id = pause(srv, camera)
        snap = httpx.get(srv.url + "/snapshot.exr?confidence=true", timeout=10)
        assert int(snap.headers["x-frame-id"]) == frame_id
        channels, _ = read_exr(snap.content)
        y_plane, sure = channels["Y"], channels["confidence"]
        assert sure[BLOCK].max() == 0 and 0 < sure.max() <= 1  # the clipped block is only a lower bound
        for x, y in ((0, 0), (223, 191), (90, 60), (10, 150), (130, 20)):
            r = httpx.get(srv.url + f"/api/pixel?x={x}&y={y}&frame={frame_id}", timeout=5)
            assert r.status_code == 200, r.text
            p = r.json()
            assert p["frame_id"] == frame_id and p["x"] == x and p["y"] == y
            assert p["values"]["Y"] == pytest.approx(float(y_plane[y, x]), rel=1e-6, abs=1e-6)
            assert p["ev"] == pytest.approx(np.log2(p["values"]["Y"] / p["mid_grey"]), abs=1e-3)
            assert p["clipped"] == (BLOCK[0].start <= y < BLOCK[0].stop and BLOCK[1].start <= x < BLOCK[1].stop)
            assert p["motion"] is False and p["confidence"] == pytest.approx(float(sure[y, x]), rel=1e-6, abs=1e-7)
        # the histogram: every pixel counted once, the clipped fraction the block's
        with concurrent.futures.ThreadPoolExecutor(4) as pool:
            answers = list(pool.map(lambda _: httpx.get(srv.url + "/api/histogram", timeout=10), range(4)))
        assert all(a.status_code == 200 for a in answers)
        h = answers[0].json()
        assert all(a.json() == h for a in answers) and calls == [1]  # once per frame for every viewer
        assert h["frame_id"] == frame_id and h["stride"] == 1 and h["pixels"] == SHAPE[0] * SHAPE[1]
        assert sum(h["counts"]["Y"]) + h["zero"]["Y"] == h["pixels"]
        assert h["clipped"] == pytest.approx(2400 / h["pixels"], abs=2 / h["pixels"])
        assert float(y_plane.min()) >= 0 and h["below_noise_floor"] == pytest.approx(
            np.mean(y_plane < h["noise_floor"]), abs=1e-9)
        # the overlay map: one byte per pixel, its clipped bit the block
        m = httpx.get(srv.url + "/overlay.map", timeout=5)
        assert m.status_code == 200 and int(m.headers["x-frame-id"]) == frame_id
        values = np.frombuffer(m.content, np.uint8).reshape(SHAPE)
        clipped = (values & 16) > 0
        assert clipped[BLOCK].all() and clipped.sum() == 2400
        assert len(set((values & 15).ravel().tolist())) >= 5  # the exposure bands of a real scene
        assert m.headers["x-confidence"] == "0" and not (values >> monitor.CONFIDENCE_SHIFT).any()
        m = httpx.get(srv.url + "/overlay.map?confidence=true", timeout=5)
        assert m.headers["x-confidence"] == "1" and int(m.headers["x-frame-id"]) == frame_id
        levels = np.frombuffer(m.content, np.uint8).reshape(SHAPE) >> monitor.CONFIDENCE_SHIFT
        assert np.array_equal(levels, (sure[..., None] >= np.float32([0.5, 0.9, 0.99])).sum(axis=-1))
        assert len(set(levels.ravel().tolist())) >= 2
        half = httpx.get(srv.url + "/overlay.map?stride=2", timeout=5)
        assert int(half.headers["x-width"]) == 112 and np.array_equal(
            np.frombuffer(half.content, np.uint8).reshape(96, 112), values[::2, ::2])


def test_frame_ids_that_are_held_and_bad_input_get_one_line():
    camera = make_camera(fps=15.0)
    with ServerThread(camera) as srv:
        srv.wait_for(lambda s: s["frames"]["reconstructed"] >= 2, timeout=20)
        first = httpx.get(srv.url + "/api/histogram", timeout=5).json()["frame_id"]
        srv.wait_for(lambda s: s["frames"]["last_frame_id"] > first)
        later = httpx.get(srv.url + "/api/pixel?x=1&y=1", timeout=5).json()
        assert later["frame_id"] > first and first in later["held"]
        assert httpx.get(srv.url + f"/api/pixel?x=1&y=1&frame={first}", timeout=5).json()["frame_id"] == first
        gone = httpx.get(srv.url + "/api/pixel?x=1&y=1&frame=999999", timeout=5)
        assert gone.status_code == 404 and "no longer held" in gone.json()["detail"]
        for query, words in (("x=-1&y=0", "x=-1"), ("x=224&y=0", "0..223"), ("x=0&y=192", "0..191"),
                             ("x=abc&y=0", "x"), ("x=0", "y"), ("x=99999999999999999999&y=0", "outside")):
            r = httpx.get(srv.url + "/api/pixel?" + query, timeout=5)
            detail = r.json()["detail"]
            assert r.status_code == 422 and isinstance(detail, str) and "\n" not in detail and words in detail, (query, detail)
        r = httpx.get(srv.url + "/overlay.map?stride=0", timeout=5)
        assert r.status_code == 422 and isinstance(r.json()["detail"], str)


def test_pixel_equals_the_exr_snapshot_colour_rec709():
    from tests.test_service_colour import ColourServer, make_colour_camera

    camera = make_colour_camera(fps=10.0)
    with ColourServer(camera) as srv:
        matrix = [1.6, -0.4, -0.2, -0.3, 1.5, -0.2, 0.0, -0.5, 1.5]
        r = httpx.put(srv.url + "/api/settings", json={"colour_matrix": matrix, "output_space": "rec709"}, timeout=5)
        assert r.status_code == 200, r.text
        frame_id = pause(srv, camera)
        snap = httpx.get(srv.url + "/snapshot.exr", timeout=10)
        assert int(snap.headers["x-frame-id"]) == frame_id
        channels, attributes = read_exr(snap.content)
        assert attributes["colourSpace"] == "rec709"
        hdr = srv.pipeline.latest().hdr.image
        for x, y in ((5, 5), (100, 80), (200, 170)):
            p = httpx.get(srv.url + f"/api/pixel?x={x}&y={y}&frame={frame_id}", timeout=5).json()
            assert p["space"] == "rec709"
            for c in "RGB":
                assert p["values"][c] == pytest.approx(float(channels[c][y, x]), rel=1e-5, abs=1e-4), (x, y, c)
            assert not np.allclose([p["values"][c] for c in "RGB"], hdr[y, x], rtol=1e-3)  # converted, not camera RGB
        h = httpx.get(srv.url + "/api/histogram", timeout=5).json()
        assert set(h["counts"]) == {"R", "G", "B"}
        assert all(sum(h["counts"][c]) + h["zero"][c] == h["pixels"] for c in "RGB")


# ----- the viewer --------------------------------------------------------------------------------

def test_viewer_readout_follows_the_cursor_and_overlays_change_the_picture(tmp_path):
    pytest.importorskip("playwright.sync_api", reason="pip install playwright (uses /usr/bin/chromium)")
    from pathlib import Path

    from tests.test_viewer import CHROMIUM, browser_page

    if not Path(CHROMIUM).exists():
        pytest.skip(f"no Chromium at {CHROMIUM}")
    camera = clipped_block_camera()
    with ServerThread(camera) as srv, browser_page(tmp_path, 700, 20_000) as page:
        page.goto(srv.url + "/")
        page.wait_for_function("document.getElementById('live').naturalWidth > 0")
        page.wait_for_function("document.getElementById('histogram').dataset.frame !== undefined")
        pause(srv, camera)
        box = page.locator("#live").bounding_box()
        scale = SHAPE[1] / box["width"]
        for fx, fy in ((90, 60), (20, 150)):  # inside the clipped block, then outside it
            page.mouse.move(box["x"] + (fx + 0.2) / scale, box["y"] + (fy + 0.2) / scale)  # (whole CSS pixels)
            page.wait_for_function(f"document.getElementById('pixel').dataset.x === '{fx}' && "
                                   f"document.getElementById('pixel').dataset.y === '{fy}'")
            text = page.text_content("#pixel")
            assert text.startswith(f"({fx}, {fy}) Y ") and ("clipped" in text) == (fy < 80 and fx >= 60), text
            assert "confidence" in text, text
        page.wait_for_function("document.getElementById('hist-info').textContent.includes('clipped')")
        before = page.locator("main").screenshot()
        page.select_option("#overlay-kind", "clipped")
        page.wait_for_function("document.getElementById('overlay').dataset.kind === 'clipped'")
        after = page.locator("main").screenshot()
        assert after != before
        # the clipped overlay paints the block magenta: read back the overlay canvas there
        rgba = page.evaluate("""() => { const c = document.getElementById('overlay');
            return Array.from(c.getContext('2d').getImageData(90, 60, 1, 1).data)
                 .concat(Array.from(c.getContext('2d').getImageData(20, 150, 1, 1).data)); }""")
        assert rgba[:4] == [255, 0, 255, 255] and rgba[7] == 0
        page.select_option("#overlay-kind", "exposure")
        page.wait_for_function("document.getElementById('overlay').dataset.kind === 'exposure'")
        assert "stops from mid-grey" in page.text_content("#legend")
        exposure = page.locator("main").screenshot()
        assert exposure not in (before, after)
        page.select_option("#overlay-kind", "confidence")
        page.wait_for_function("document.getElementById('overlay').dataset.kind === 'confidence'")
        assert "signal-to-noise" in page.text_content("#legend")
        assert page.locator("main").screenshot() not in (before, after, exposure)
        # the clipped block is only a lower bound: confidence 0, the lowest level's colour
        rgba = page.evaluate("""() => Array.from(document.getElementById('overlay').getContext('2d')
            .getImageData(90, 60, 1, 1).data)""")
        assert rgba[:3] == list(monitor.CONFIDENCE_LEVELS[0][1]) and rgba[3] > 0
        page.check("#zoom11")
        assert page.evaluate("document.getElementById('live').getBoundingClientRect().width") == SHAPE[1]


def test_viewer_offers_the_hdr_view_on_an_hdr_display(tmp_path):
    """Where the display reports ``dynamic-range: high`` (Chromium told its screen is HDR10), the viewer offers
    the HDR view, which shows the newest frame as the AVIF snapshot in place of the SDR preview; on an SDR
    display it does not offer it."""
    pytest.importorskip("playwright.sync_api", reason="pip install playwright (uses /usr/bin/chromium)")
    from pathlib import Path

    from svelive import hdr_encode
    from tests.test_viewer import CHROMIUM, browser_page

    if not Path(CHROMIUM).exists():
        pytest.skip(f"no Chromium at {CHROMIUM}")
    if not hdr_encode.available():
        pytest.skip(f"HDR snapshots need imagecodecs: {hdr_encode.INSTALL}")
    camera = clipped_block_camera()
    with ServerThread(camera) as srv:
        with browser_page(tmp_path / "sdr", 700, 20_000) as page:
            page.goto(srv.url + "/")
            page.wait_for_function("document.getElementById('live').naturalWidth > 0")
            assert not page.evaluate("matchMedia('(dynamic-range: high)').matches")
            assert page.locator("#hdr-view-label").is_hidden() and "HDR display" not in page.text_content("#snapavif")
        with browser_page(tmp_path / "hdr", 700, 20_000, ("--force-color-profile=hdr10",)) as page:
            page.goto(srv.url + "/")
            page.wait_for_function("document.getElementById('live').naturalWidth > 0")
            assert page.evaluate("matchMedia('(dynamic-range: high)').matches")
            assert "(HDR display)" in page.text_content("#snapavif")
            page.check("#hdr-view")
            page.wait_for_function("!document.getElementById('hdr').hidden && "
                                   "document.getElementById('hdr').naturalWidth > 0")
            assert page.evaluate("document.getElementById('hdr').naturalWidth") == SHAPE[1]
            frame = int(page.get_attribute("#hdr", "data-frame"))
            box, live = page.locator("#hdr").bounding_box(), page.locator("#live").bounding_box()
            assert abs(box["width"] - live["width"]) < 1 and abs(box["x"] - live["x"]) < 1  # in the preview's place
            page.wait_for_function(f"parseInt(document.getElementById('hdr').dataset.frame) > {frame}")  # it follows
            page.uncheck("#hdr-view")
            assert page.locator("#hdr").is_hidden()
