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
