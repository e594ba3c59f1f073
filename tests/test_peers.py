"""benchmarks/peers.py without cr2hdr: the DNG it writes for cr2hdr, its scores, and its message when
cr2hdr is not built."""

from __future__ import annotations

import shutil
import subprocess

import numpy as np
import pytest

pytest.importorskip("tifffile")

from benchmarks import peers  # noqa: E402
from svelive.core.cfa import ColourFilter  # noqa: E402

RGGB = ColourFilter.parse("RGGB")


def frame_12bit(shape: tuple[int, int] = (40, 64), seed: int = 0) -> np.ndarray:
    """A random 12-bit frame, uint16 (H, W), every value of the range likely."""
    return np.random.default_rng(seed).integers(0, 4096, shape).astype(np.uint16)


def written_dng(tmp_path, raw: np.ndarray, layout: peers.CanonLayout = peers.CanonLayout()):
    """``raw`` as Canon-like 14 bits (uint16 with margins) and the DNG file it was written to."""
    raw14 = peers.canon_raw(raw, peers.BENCH_SENSOR, layout, np.random.default_rng(1))
    path = tmp_path / "frame.dng"
    peers.write_dng(path, raw14, RGGB, layout, layout.white(peers.BENCH_SENSOR))
    return raw14, path


def test_canon_raw_maps_12_bits_to_14_with_optical_black_margins():
    layout = peers.CanonLayout()
    raw = frame_12bit()
    raw14 = peers.canon_raw(raw, peers.BENCH_SENSOR, layout, np.random.default_rng(1))
    assert raw14.shape == (layout.top + 40, layout.left + 64) and raw14.dtype == np.uint16
    np.testing.assert_array_equal(raw14[layout.top:, layout.left:], 2048 + 3 * raw.astype(np.int64))
    assert layout.white(peers.BENCH_SENSOR) == 2048 + 3 * 4095 <= 2**14 - 1
    black = raw14[:layout.top].astype(np.float64)  # read noise around the black level, not clipped
    assert abs(black.mean() - 2048) < 0.5 and 2.0 < black.std() < 6.0 and black.min() < 2048


def test_dng_round_trips_values_cfa_pattern_and_levels(tmp_path):
    raw14, path = written_dng(tmp_path, frame_12bit())
    dng = peers.read_dng(path)
    np.testing.assert_array_equal(dng.values, raw14)
    np.testing.assert_array_equal(dng.cfa, RGGB.tile)
    assert (dng.black, dng.white) == (2048, 2048 + 3 * 4095)
    assert dng.active == (40, 128, raw14.shape[0], raw14.shape[1])


def test_dng_tags_are_those_of_a_cfa_dng(tmp_path):
    import tifffile

    _, path = written_dng(tmp_path, frame_12bit())
    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        tags = {t.code: t.value for t in page.tags}
    assert page.photometric == peers.PHOTOMETRIC_CFA and page.bitspersample == 16
    assert tuple(tags[peers.TAG["DNGVersion"]]) == (1, 4, 0, 0)
    assert tuple(tags[peers.TAG["CFARepeatPatternDim"]]) == (2, 2)
    assert bytes(tags[peers.TAG["CFAPattern"]]) == bytes([0, 1, 1, 2])
    assert tags[peers.TAG["Make"]] == "Canon" and tags[peers.TAG["Model"]] == "Canon EOS 5D Mark III"


@pytest.mark.skipif(shutil.which("dcraw") is None, reason="dcraw (the reader cr2hdr uses) is not installed")
def test_dcraw_reads_the_dng_as_cr2hdr_asks_it(tmp_path):
    """cr2hdr takes the margins from `dcraw -i -v` and the values from `dcraw -4 -E -c` (a PGM)."""
    raw14, path = written_dng(tmp_path, frame_12bit())
    info = subprocess.run(["dcraw", "-v", "-i", "-t", "0", str(path)], capture_output=True, text=True).stdout
    assert "Full size:    192 x 80" in info and "Output size:   64 x 40" in info and "RG/GB" in info
    pgm = subprocess.run(["dcraw", "-4", "-E", "-c", "-t", "0", str(path)], capture_output=True).stdout
    values = np.frombuffer(pgm[-raw14.size * 2:], ">u2").reshape(raw14.shape)
    np.testing.assert_array_equal(values, raw14)


def test_scores_of_the_truth_are_perfect_and_chroma_error_sees_a_white_light():
    truth = np.random.default_rng(2).uniform(1, 100, (32, 32, 3)).astype(np.float32)
    got = peers.scores(truth, peers.sites(truth, RGGB), truth, RGGB, clip=1000.0)
    assert got.pu21_site == got.pu21_rgb == float("inf") and got.chroma_p1 == 0.0
    orange = np.zeros((10, 10, 3), np.float32) + 0.01
    orange[5, 5] = (60, 30, 5)
    grey = orange.copy()
    grey[5, 5] = 30  # the light gone white: (r, b) from (0.63, 0.05) to (1/3, 1/3)
    assert peers.chroma_error(grey, orange, clip=1000.0) == pytest.approx(np.hypot(60 / 95 - 1 / 3, 5 / 95 - 1 / 3))


def test_fit_scale_recovers_cr2hdr_output_unit_and_its_iso_difference_is_read():
    truth = np.random.default_rng(3).uniform(1, 4000, (20, 20)).astype(np.float32)
    assert peers.fit_scale(truth / 12.0, truth, clip=5000.0, display=0.25) == pytest.approx(12.0, rel=1e-5)
    assert peers.iso_difference("Black level     : 2047\nISO difference  : 3.03 EV (817)\n") == 3.03
    assert peers.iso_difference("Doesn't look like interlaced ISO") is None


def test_without_cr2hdr_says_so_in_one_line_and_fails(tmp_path, capsys):
    assert peers.main(["--cr2hdr", str(tmp_path / "cr2hdr"), "--quick"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "cr2hdr is not built" in err and "scripts/build-cr2hdr.sh" in err
