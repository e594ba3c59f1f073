"""Image-sequence, demo and V4L2 sources, spec parsing, and closing from another thread."""

from __future__ import annotations

import glob
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from svelive.capture import open_source, parse_spec
from svelive.core.errors import SveliveError


def write_sequence(folder: Path, n: int, dtype: type = np.uint16) -> list[np.ndarray]:
    folder.mkdir(exist_ok=True)
    imgs = []
    for i in range(n):
        img = ((np.arange(12 * 16).reshape(12, 16) * 37 + i * 1000) % 4096).astype(dtype)
        cv2.imwrite(str(folder / f"f{i}.png"), img)  # f10 sorts after f9: natural order
        imgs.append(img)
    return imgs


def test_spec_parsing() -> None:
    assert parse_spec("gige") == ("gige", None) and parse_spec("gige:GV01") == ("gige", "GV01")
    assert parse_spec("images:/a/*.png") == ("images", "/a/*.png") and parse_spec("demo") == ("demo", None)
    for bad, msg in [("", "empty"), ("usb:3", "unknown source"), ("v4l2", "needs an argument"),
                     ("replay:", "needs an argument")]:
        with pytest.raises(SveliveError, match=msg):
            parse_spec(bad)


def test_image_sequence_order_pacing_and_loop(tmp_path: Path) -> None:
    imgs = write_sequence(tmp_path / "seq", 11)
    with open_source(f"images:{tmp_path / 'seq'}") as s:
        got = list(s)
        assert s.stats()["state"] == "ended" and s.stats()["frames"] == 11
    assert len(got) == 11 and all(np.array_equal(g.raw, i) for g, i in zip(got, imgs))
    assert got[0].raw.dtype == np.uint16 and got[0].pixel_format == "Mono16"
    with open_source(f"images:{tmp_path / 'seq'}/f1*.png", fps=50, loop=True, bits=12) as s:
        t = time.monotonic()
        got = list(s.frames(limit=6))
        elapsed = time.monotonic() - t
    assert [g.frame_id for g in got] == list(range(6)) and got[0].sensor.bits == 12
    assert np.array_equal(got[2].raw, imgs[1])  # f1, f10 then loop to f1
    assert 0.08 < elapsed < 0.5  # 5 intervals of 20 ms


def test_image_sequence_bad_input(tmp_path: Path) -> None:
    with pytest.raises(SveliveError, match="no image files"):
        open_source(f"images:{tmp_path}").open()
    write_sequence(tmp_path / "s", 2)
    cv2.imwrite(str(tmp_path / "s" / "f2.png"), np.zeros((5, 5), np.uint16))
    with pytest.raises(SveliveError, match="f2.png: is 5x5 uint16 but the sequence started with 16x12"):
        list(open_source(f"images:{tmp_path / 's'}"))
    cv2.imwrite(str(tmp_path / "c.png"), np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(SveliveError, match="3 channels"):
        open_source(f"images:{tmp_path / 'c.png'}").open()
    (tmp_path / "x.png").write_bytes(b"not a png")
    with pytest.raises(SveliveError, match="not a readable"):
        open_source(f"images:{tmp_path / 'x.png'}").open()
    with pytest.raises(SveliveError, match="unknown option"):
        open_source("images:x", speed=2)


def test_demo_renders_moving_hdr_scene_at_rate() -> None:
    with open_source("demo", width=320, height=180, fps=30, cfa="none") as s:  # the monochrome demo
        t = time.monotonic()
        frames = list(s.frames(limit=16))
        elapsed = time.monotonic() - t
        stats = s.stats()
    # Paced by its schedule, not by the machine's speed (a loaded machine only makes it later):
    # scene time steps 1/30 s, delivery never runs ahead of it, and the reported rate is the
    # rate the frames were really handed out at.
    steps = np.diff([f.device_time_ns for f in frames])
    assert np.all(steps == pytest.approx(1e9 / 30, abs=1))
    assert elapsed >= 15 / 30 - 0.01 and stats["target_fps"] == 30
    delivered = np.diff([f.host_time_ns for f in frames]).mean() / 1e9
    assert stats["fps"] == pytest.approx(1 / delivered, rel=0.05)
    raw = frames[0].raw
    assert raw.shape == (180, 320) and raw.dtype == np.uint16 and frames[0].pixel_format == "Mono12"
    assert s.pattern == "1,4/16,64" and frames[0].sensor.bits == 12
    assert raw.max() == 4095 and np.percentile(raw, 5) < 200  # saturated highlights and dark shadows
    assert np.abs(frames[-1].raw.astype(int) - raw.astype(int)).mean() > 5  # it moves
    long_px = raw[1::2, 1::2]  # exposure 64 of the tile 1,4/16,64
    assert (long_px == 4095).mean() > (raw[0::2, 0::2] == 4095).mean()


def test_demo_is_a_colour_sve_camera_at_the_scene_native_size() -> None:
    from svelive.capture.demo import DemoSource

    with open_source("demo", fps=0) as s:
        frames = list(s.frames(limit=3))
        stats = s.stats()
    raw = frames[0].raw
    camera = frames[0].camera
    assert raw.shape == (540, 960) and raw.dtype == np.uint16  # the shipped crop less its motion margin
    assert frames[0].pixel_format == "BayerRG12" and camera.cfa.name == "RGGB" and stats["cfa"] == "RGGB"
    assert str(camera.pattern) == "1/1/8/8" and s.pattern == "1/1/8/8"  # the dual-ISO exposures
    assert raw.max() == 4095 and np.percentile(raw, 1) < 20  # the light saturates, shadows stay dark
    # colour, not grey: the three channels of the scene the sensor sees differ
    source = DemoSource("demo", fps=0)
    source.open()
    rgb = source.radiance(0.0)
    source.close()
    assert rgb.shape == (540, 960, 3)
    means = rgb.reshape(-1, 3).mean(axis=0)
    assert np.ptp(means) > 0.1 * means.mean()
    # each filter site records its own channel: compare the raw with the mosaic of that radiance
    mosaic = source.mosaic(0.0) * source._exposure
    assert np.array_equal(mosaic[0::2, 0::2], (rgb[0::2, 0::2, 0] * source._exposure[0::2, 0::2]))
    assert np.array_equal(mosaic[1::2, 1::2], (rgb[1::2, 1::2, 2] * source._exposure[1::2, 1::2]))


def test_demo_noise_follows_the_sensor_model() -> None:
    """The fast render's raw values are the mosaic of radiance() times the exposure, plus noise
    of the sensor model's variance: standardised residuals have mean 0 and deviation 1."""
    from svelive.capture.demo import DemoSource

    for cfa in ("RGGB", "none"):
        s = DemoSource("demo", width=320, height=200, fps=0, cfa=cfa, seed=3)
        s.open()
        raw = s._render(1.5).astype(np.float64)
        signal = s.mosaic(1.5).astype(np.float64) * s._exposure
        s.close()
        sensor = s.sensor
        var = sensor.signal_variance(signal)
        inside = (signal + 5 * np.sqrt(var) < sensor.range_dn) & (signal > 20)  # away from clipping and zero
        z = (raw - sensor.black_level - signal)[inside] / np.sqrt(var[inside])
        assert inside.sum() > 20000
        assert abs(z.mean()) < 0.02 and z.std() == pytest.approx(1.0, abs=0.03)
        clipped = signal > sensor.range_dn + 5 * np.sqrt(sensor.signal_variance(sensor.range_dn))
        assert clipped.any() and np.all(raw[clipped] == sensor.white_level)


def test_demo_exact_render_agrees_with_the_fast_one() -> None:
    """exact=True (Poisson-Gaussian through svelive.simulate) and the fast Gaussian render give
    the same mean per filter site and exposure (within 1 %) of the same scene."""
    for cfa in ("RGGB", "none"):
        means = []
        for exact in (True, False):
            with open_source("demo", width=320, height=200, fps=0, cfa=cfa, exact=exact, seed=5) as s:
                raw = s.read().raw.astype(np.float64)
            means.append([raw[i::4, j::2].mean() for i in range(4) for j in range(2)])
        np.testing.assert_allclose(means[0], means[1], rtol=0.01)


def test_demo_light_has_no_square_edge() -> None:
    """The moving light is a Gaussian over the whole frame: no window edge where it steps to zero."""
    from svelive.capture.demo import DemoSource

    s = DemoSource("demo", width=640, height=360, fps=0, cfa="none")
    s.open()
    with_light = s.radiance(2.0).astype(np.float64)
    s._light = np.zeros_like(s._light)
    scene = s.radiance(2.0).astype(np.float64)
    s.close()
    light = with_light - scene
    # along the row through the light's peak its profile falls off smoothly: no step between neighbours
    y, x = np.unravel_index(np.argmax(light), light.shape)
    profile = light[y]
    steps = np.abs(np.diff(profile))
    far = profile < 1e-3 * profile.max()
    assert far.any() and steps[far[1:] & far[:-1]].max() < 1e-3 * profile.max()
    assert light.min() >= 0 and light[y, x] > 1000


def test_demo_bayer_option_behaves_like_a_bayer_camera() -> None:
    from svelive.capture.demo import DemoSource

    with open_source("demo", width=64, height=48, fps=0, pixel_format="BayerGR16") as s:
        frame = s.read()
    assert frame.pixel_format == "BayerGR16" and frame.camera.cfa.name == "GRBG" and frame.sensor.bits == 16
    assert frame.raw.max() == 65535 and str(frame.camera.pattern) == "1/1/8/8"
    with open_source("demo", width=64, height=48, fps=0, pixel_format="Mono12") as s:
        assert s.read().camera.cfa is None and s.pattern == "1,4/16,64"
    with open_source("demo", width=64, height=48, fps=0, pattern="quad-bayer") as s:
        frame = s.read()
    assert frame.camera.cfa.name == "quad-RGGB" and frame.pixel_format == "Mono12"  # no PFNC name for it
    # the contradictions a camera refuses
    with pytest.raises(SveliveError, match="BayerRG12, a Bayer format .* cannot be reconstructed as monochrome"):
        DemoSource("demo", pixel_format="BayerRG12", cfa="none")
    with pytest.raises(SveliveError, match="Mono12, a monochrome format, but a colour filter"):
        DemoSource("demo", pixel_format="Mono12", cfa="RGGB")
    with pytest.raises(SveliveError, match="colour filter GRBG at this region.*--cfa RGGB"):
        DemoSource("demo", pixel_format="BayerGR12", cfa="RGGB")
    with pytest.raises(SveliveError, match="layout dual-iso has the colour filter RGGB.*--cfa none"):
        DemoSource("demo", pattern="dual-iso", cfa="none")
    with pytest.raises(SveliveError, match="unknown scene 'moon'"):
        DemoSource("demo", scene="moon")
    with open_source("demo:desk", width=64, height=48, fps=0) as s:  # the 256x256 crops still work
        assert s.config.scene == "desk" and s.read().raw.shape == (48, 64)


def test_close_from_another_thread_ends_iteration_quickly(tmp_path: Path) -> None:
    """close() wakes a reader waiting for the next frame: with 50 s between frames, the
    reader must end within the join's 10 s, so no tight wall-clock bound is needed."""
    write_sequence(tmp_path / "seq", 2)
    for spec, opts in [("demo", {"width": 64, "height": 48, "fps": 0.02}),
                       (f"images:{tmp_path / 'seq'}", {"fps": 0.02, "loop": True})]:
        source = open_source(spec, **opts)
        got: list[int] = []
        th = threading.Thread(target=lambda: got.extend(f.frame_id for f in source))
        th.start()
        for _ in range(100):  # the first frame comes at once; then the reader waits ~50 s
            if got:
                break
            time.sleep(0.05)
        source.close()
        th.join(10)
        assert not th.is_alive()
        assert source.stats()["state"] == "closed" and got == [0]


@pytest.mark.skipif(not glob.glob("/dev/video*"), reason="no /dev/video* device on this machine")
def test_v4l2_device_delivers_raw_frames() -> None:
    device = sorted(glob.glob("/dev/video*"))[0]
    with open_source(f"v4l2:{device}", pixel_format="GREY") as s:
        frame = s.read(timeout=5)
    assert frame.raw.ndim == 2 and frame.raw.dtype in (np.uint8, np.uint16)


def test_v4l2_missing_device_is_a_clear_error() -> None:
    with pytest.raises(SveliveError, match="no such V4L2 device"):
        open_source("v4l2:/dev/video-does-not-exist").open()
