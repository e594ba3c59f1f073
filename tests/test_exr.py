import os

import numpy as np
import pytest

from svelive import SveliveError
from svelive.exr import exr_bytes, read_exr, read_luminance, write_exr


def test_write_read_float32_with_attributes(tmp_path):
    y = np.random.default_rng(0).random((5, 7)).astype(np.float32) * 1e4
    path = write_exr(tmp_path / "a.exr", {"Y": y, "confidence": y / y.max()},
                     {"pattern": "1,4/16,64", "method": "weighted", "blackLevel": 64.0})
    channels, header = read_exr(path)
    assert np.array_equal(channels["Y"], y)
    assert header["pattern"] == "1,4/16,64" and header["method"] == "weighted" and header["blackLevel"] == 64.0
    assert "ZIP" in str(header["compression"])
    assert [p.name for p in tmp_path.iterdir()] == ["a.exr"]  # no temporary left behind


def test_half_and_bytes_round_trip():
    y = np.array([[0.5, 1.0], [1000.0, 3.0e4]], np.float32)
    data = exr_bytes({"Y": y}, half=True)
    channels, _ = read_exr(data)
    assert channels["Y"].dtype == np.float32
    assert np.allclose(channels["Y"], y, rtol=1e-3)


def test_failed_write_leaves_nothing(tmp_path):
    target = tmp_path / "b.exr"
    with pytest.raises(SveliveError):
        write_exr(target, {"Y": np.zeros((2, 2)), "Z": np.zeros((3, 3))})
    with pytest.raises(SveliveError, match="does not exist"):
        write_exr(tmp_path / "missing" / "c.exr", {"Y": np.zeros((2, 2))})
    assert list(tmp_path.iterdir()) == []


def test_unreadable_inputs(tmp_path):
    bad = tmp_path / "bad.exr"
    bad.write_bytes(b"not an exr at all")
    with pytest.raises(SveliveError, match="not a readable EXR"):
        read_exr(bad)
    with pytest.raises(SveliveError, match="no such EXR"):
        read_exr(tmp_path / "none.exr")


def test_luminance_from_rgb(tmp_path):
    r = np.full((2, 2), 1.0, np.float32)
    path = write_exr(tmp_path / "rgb.exr", {"R": r, "G": 2 * r, "B": 3 * r})
    assert np.allclose(read_luminance(path), 0.2126 + 2 * 0.7152 + 3 * 0.0722)


def test_rgb_channels_typed_attributes_and_chromaticities(tmp_path):
    from svelive.exr import REC709_CHROMATICITIES, image_channels, read_rgb

    rgb = np.random.default_rng(1).random((6, 5, 3)).astype(np.float32) * 1e3
    channels = image_channels(rgb)
    assert list(channels) == ["R", "G", "B"]
    path = write_exr(tmp_path / "rgb.exr", {**channels, "confidence": rgb[:, :, 0] / 1e3},
                     {"chromaticities": REC709_CHROMATICITIES, "whiteBalance": (2.0, 1.0, 1.5),
                      "colourMatrix": np.eye(3), "colourSpace": "rec709", "whiteBalanceApplied": 1})
    back, header = read_exr(path)
    assert set(back) == {"R", "G", "B", "confidence"}
    assert np.array_equal(read_rgb(path), rgb)
    assert header["chromaticities"] == pytest.approx(REC709_CHROMATICITIES, abs=1e-6)
    assert header["whiteBalance"].tolist() == [2.0, 1.0, 1.5] and header["colourMatrix"].shape == (3, 3)
    assert header["colourSpace"] == "rec709" and header["whiteBalanceApplied"] == 1
    half, _ = read_exr(exr_bytes(channels, half=True))
    assert np.allclose(np.dstack([half[c] for c in "RGB"]), rgb, rtol=1e-3)


def test_image_channels_and_read_rgb_of_mono(tmp_path):
    from svelive.exr import image_channels, read_rgb

    y = np.arange(12, dtype=np.float32).reshape(3, 4)
    assert list(image_channels(y)) == ["Y"]
    grey = read_rgb(write_exr(tmp_path / "y.exr", {"Y": y}))
    assert grey.shape == (3, 4, 3) and np.array_equal(grey[:, :, 2], y)
    with pytest.raises(SveliveError, match=r"\(H, W, 3\)"):
        image_channels(np.zeros((3, 4, 2)))
    with pytest.raises(SveliveError, match="neither R, G, B nor a Y"):
        read_rgb(write_exr(tmp_path / "z.exr", {"Z": y}))
    with pytest.raises(SveliveError, match="8 numbers"):
        write_exr(tmp_path / "c.exr", {"Y": y}, {"chromaticities": (0.64, 0.33)})


def test_standard_attributes_one_name_for_each(tmp_path):
    from svelive import Camera, Sensor, __version__
    from svelive.exr import STANDARD_ATTRIBUTES, UNITS, standard_attributes

    camera = Camera.build("dual-iso", sensor=Sensor(12, 64, 4000))
    attrs = standard_attributes(camera, "weighted", frame_id=7, timestamp=1700000000.1234567,
                                extra={"whiteBalance": (2.0, 1.0, 1.5)})
    assert set(attrs) - {"whiteBalance"} <= set(STANDARD_ATTRIBUTES)
    assert attrs["units"] == UNITS and attrs["method"] == "weighted" and attrs["pattern"] == "1/1/8/8"
    assert attrs["cfa"] == "RGGB" and attrs["blackLevel"] == 64 and attrs["whiteLevel"] == 4000
    assert attrs["frameId"] == 7 and attrs["timestamp"] == "1700000000.123457" and attrs["svelive"] == __version__
    write_exr(tmp_path / "a.exr", {"Y": np.zeros((2, 2), np.float32)}, attrs)
    _, header = read_exr(tmp_path / "a.exr")
    assert header["frameId"] == 7 and header["units"] == UNITS and header["timestamp"] == "1700000000.123457"

    mono = standard_attributes(Camera.build("1,4/16,64"), "adaptive")
    assert "cfa" not in mono and "frameId" not in mono and "timestamp" not in mono
    with pytest.raises(SveliveError, match="standard"):
        standard_attributes(camera, "weighted", extra={"method": "other"})


def test_compressing_on_threads_writes_the_same_bytes():
    import OpenEXR

    from svelive.exr import compress_on, exr_bytes

    rng = np.random.default_rng(3)
    image = np.cumsum(rng.random((300, 480), np.float32), axis=1).astype(np.float32)
    channels = {"Y": image, "motion": (image > image.mean()).astype(np.float32)}
    before = OpenEXR.global_thread_count()
    try:
        assert compress_on(0) == 0
        alone = exr_bytes(channels, {"note": "x"})
        assert compress_on() == (os.cpu_count() or 1) and OpenEXR.global_thread_count() == compress_on()
        threaded = exr_bytes(channels, {"note": "x"})
        with pytest.raises(SveliveError, match="threads"):
            compress_on(-1)
    finally:
        OpenEXR.set_global_thread_count(before)
    assert threaded == alone


def test_one_frame_writer_white_balance_output_space_attributes(tmp_path):
    """svelive.frame_exr: the file and the bytes are one; a colour frame's channels in the output space with the
    white balance given, then the planes; standard attributes, the frame's own, then the colour ones."""
    from svelive import Camera
    from svelive.frame_exr import FrameInfo, frame_exr_bytes, single_frame_balance, write_frame_exr
    from svelive.whitebalance import ColourSettings

    rgb = np.random.default_rng(4).random((6, 8, 3)).astype(np.float32) * 100
    info = FrameInfo(Camera.build("dual-iso"), "weighted", frame_id=3, timestamp=12.5, attributes={"note": "x"})
    colour = ColourSettings((2.0, 1.0, 1.5), "1,0,0,0,1,0,0,0,1", "rec709")
    balance = single_frame_balance(rgb, colour)
    planes = {"confidence": np.ones((6, 8), np.float32)}
    path = write_frame_exr(tmp_path / "f.exr", rgb, info, colour, balance, planes)
    assert path.read_bytes() == frame_exr_bytes(rgb, info, colour, balance, planes)
    channels, header = read_exr(path)
    assert set(channels) == {"R", "G", "B", "confidence"}
    np.testing.assert_allclose(channels["R"], 2 * rgb[:, :, 0], rtol=1e-6)
    assert header["frameId"] == 3 and header["cfa"] == "RGGB" and header["note"] == "x"
    assert header["colourSpace"] == "rec709" and header["whiteBalanceMode"] == "fixed"
    mono = np.ones((6, 8), np.float32)
    assert single_frame_balance(mono, colour) is None
    channels, header = read_exr(frame_exr_bytes(mono, FrameInfo(Camera.build("1,4/16,64"), "weighted"), colour, None))
    assert set(channels) == {"Y"} and "colourSpace" not in header and "frameId" not in header
