"""Issue 13's defects of the library and the core command line, one test each (each failed before its fix).

Outputs never replace what is not a regular file (item 1); bad input is a one-line
error, never a traceback or a silently wrong output (item 12); version and EXR
attribute vocabulary (item 17).
"""

from __future__ import annotations

import os
import stat
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

import svelive
from svelive.core.atomic import atomic_path, write_bytes_atomic
from svelive.core.errors import SveliveError
from svelive.exr import read_exr, write_exr


def run(*args: object, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "svelive.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, timeout=120)


def one_line_error(out: subprocess.CompletedProcess, *words: str) -> None:
    assert out.returncode == 2, (out.returncode, out.stderr)
    assert "Traceback" not in out.stderr and len(out.stderr.strip().splitlines()) == 1, out.stderr
    for word in words:
        assert word in out.stderr, out.stderr


@pytest.fixture
def raw_png(tmp_path: Path) -> Path:
    path = tmp_path / "raw.png"
    rng = np.random.default_rng(0)
    assert cv2.imwrite(str(path), rng.integers(0, 4096, (16, 16)).astype(np.uint16))
    return path


# ----- item 1: an output replaces only a regular file ---------------------------------------

def _fifo(tmp_path: Path) -> Path:
    path = tmp_path / "fifo"
    os.mkfifo(path)
    return path


def _char_device(tmp_path: Path) -> Path:
    """A /dev/null-like character device node in tmp_path (root only; the real /dev is not touched)."""
    if os.geteuid() != 0:
        pytest.skip("creating a device node needs root")
    path = tmp_path / "null"
    os.mknod(path, 0o666 | stat.S_IFCHR, os.makedev(1, 3))
    return path


@pytest.mark.parametrize("make, kind", [(_fifo, "FIFO"), (_char_device, "character device")])
def test_reconstruct_refuses_a_non_regular_output_and_leaves_it(raw_png: Path, tmp_path: Path, make, kind: str) -> None:
    target = make(tmp_path)
    before = os.lstat(target)
    out = run("reconstruct", raw_png, "--pattern", "1,4/16,64", "-o", target)
    one_line_error(out, kind, str(target))
    after = os.lstat(target)
    assert stat.S_IFMT(after.st_mode) == stat.S_IFMT(before.st_mode) and after.st_rdev == before.st_rdev
    assert after.st_ino == before.st_ino
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temporary left behind


@pytest.mark.parametrize("make", [_fifo, _char_device])
def test_every_atomic_writer_refuses_a_non_regular_target(tmp_path: Path, make) -> None:
    target = make(tmp_path)
    ino = os.lstat(target).st_ino
    with pytest.raises(SveliveError, match="an output replaces only a regular file"):
        write_bytes_atomic(target, b"data")
    with pytest.raises(SveliveError, match="an output replaces only a regular file"):
        write_exr(target, {"Y": np.zeros((2, 2), np.float32)})
    from svelive.core.atomic import check_output_target

    with pytest.raises(SveliveError, match="an output replaces only a regular file"):
        check_output_target(target)
    assert os.lstat(target).st_ino == ino


def test_a_directory_target_is_refused(tmp_path: Path) -> None:
    with pytest.raises(SveliveError, match="is a directory"):
        write_bytes_atomic(tmp_path, b"x")


def test_a_symlink_is_refused_unless_followed(raw_png: Path, tmp_path: Path) -> None:
    real = tmp_path / "real.exr"
    real.write_bytes(b"old")
    link = tmp_path / "link.exr"
    link.symlink_to(real)
    out = run("reconstruct", raw_png, "--pattern", "1,4/16,64", "-o", link)
    one_line_error(out, "symbolic link", str(real))
    assert link.is_symlink() and real.read_bytes() == b"old"

    # asked for: the link's target is replaced atomically in its own directory, the link stays
    write_bytes_atomic(link, b"new", follow_symlinks=True)
    assert link.is_symlink() and real.read_bytes() == b"new"
    # a link to a FIFO is refused even when followed
    fifo = _fifo(tmp_path)
    to_fifo = tmp_path / "to-fifo"
    to_fifo.symlink_to(fifo)
    with pytest.raises(SveliveError, match="FIFO"):
        write_bytes_atomic(to_fifo, b"x", follow_symlinks=True)
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)


def test_a_regular_file_is_still_replaced_atomically(tmp_path: Path) -> None:
    target = tmp_path / "out.bin"
    target.write_bytes(b"old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"half")
            raise RuntimeError("failed half way")
    assert target.read_bytes() == b"old"
    write_bytes_atomic(target, b"new")
    assert target.read_bytes() == b"new" and sorted(p.name for p in tmp_path.iterdir()) == ["out.bin"]


# ----- item 12: one-line errors ------------------------------------------------------------

def _pgm(path: Path, width: int, height: int, maxval: int = 65535, data: bytes = b"\0" * 100) -> Path:
    path.write_bytes(f"P5\n# a comment\n{width} {height}\n{maxval}\n".encode() + data)
    return path


@pytest.mark.parametrize("width, height, words", [(100_000, 100_000, "more than"), (3000, 3000, "truncated")])
def test_a_pgm_header_claiming_a_huge_or_missing_frame(tmp_path: Path, width: int, height: int, words: str) -> None:
    path = _pgm(tmp_path / "big.pgm", width, height)
    out = run("reconstruct", path, "--pattern", "1,4/16,64", "-o", tmp_path / "out.exr")
    one_line_error(out, words, f"{width}x{height}")
    out = run("record", "--source", f"images:{tmp_path}", "--pattern", "1,4/16,64", "-o", tmp_path / "r.sverec",
              "--frames", "1")
    assert out.returncode == 2 and "Traceback" not in out.stderr and words in out.stderr, out.stderr


def test_a_png_header_claiming_a_huge_frame(tmp_path: Path) -> None:
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    path = tmp_path / "big.png"
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 100_000, 100_000, 16, 0, 0, 0, 0))
                     + chunk(b"IEND", b""))
    one_line_error(run("reconstruct", path, "--pattern", "1,4/16,64", "-o", tmp_path / "o.exr"), "100000x100000")


def test_a_readable_pgm_still_reads(tmp_path: Path) -> None:
    from svelive.capture.images import read_image

    data = np.arange(12, dtype=">u2").reshape(3, 4)
    path = _pgm(tmp_path / "ok.pgm", 4, 3, 4095, data.tobytes())
    assert np.array_equal(read_image(str(path)), data)


def test_demo_of_an_absurd_size_is_refused(tmp_path: Path) -> None:
    out = run("record", "--source", "demo", "--width", "100000", "--height", "100000", "-o", tmp_path / "x.sverec",
              "--frames", "1")
    assert out.returncode == 2 and "Traceback" not in out.stderr and "--width/--height" in out.stderr, out.stderr
    from svelive.capture import open_source

    with pytest.raises(SveliveError, match="larger than the demo renders"):
        open_source("demo", width=100_000).open()


@pytest.mark.parametrize("args, words", [
    (["--pattern", "1e-9,1/1,1"], "2^24"),
    (["--pattern", "1e-30,1e-30"], "2^-24"),
])
def test_info_on_exposures_float32_cannot_hold(args: list[str], words: str) -> None:
    one_line_error(run("info", *args), words)


def test_info_counts_levels_of_any_accepted_pattern_at_16_bits() -> None:
    out = run("info", "--pattern", "0.123457,0.234567/0.345679,0.456791", "--bits", "16")
    assert out.returncode == 0, out.stderr
    assert "16-bit" in out.stdout and "unique levels Q    2" in out.stdout


def test_info_reports_the_requested_pattern_and_bits_not_the_papers_example() -> None:
    out = run("info", "--pattern", "1,2/4,8", "--bits", "10")
    assert out.returncode == 0, out.stderr
    assert "1,2/4,8" in out.stdout and "for 10 bits" in out.stdout and "10-bit" in out.stdout
    assert "869" not in out.stdout and "8 bits" not in out.stdout
    assert "for 12 bits" in run("info", "--pattern", "1,4/16,64").stdout  # the default depth is the sensor's


def test_reconstruct_refuses_a_pattern_it_would_reconstruct_as_zeros(raw_png: Path, tmp_path: Path) -> None:
    out = run("reconstruct", raw_png, "--pattern", "1e-300,1/1,1", "-o", tmp_path / "zero.exr")
    one_line_error(out, "2^24")
    assert not (tmp_path / "zero.exr").exists()


def test_unique_levels_are_exact_at_the_ratio_limit() -> None:
    from svelive.core.pattern import MAX_RATIO, Pattern, unique_levels

    # exposures 1 and 2^24 at 16 bits: the levels q and q / 2^24 coincide only at q = 0
    assert unique_levels(Pattern.parse(f"1,{MAX_RATIO:.0f}"), 16) == 2 * 2**16 - 1
    assert unique_levels(Pattern.parse("nayar-r4"), 8) == 832
    with pytest.raises(SveliveError, match="2\\^24"):
        Pattern.parse(f"1,{MAX_RATIO * 1.01:.0f}")


@pytest.mark.parametrize("sensor", [[12, 0], [], 0, "12", {"bits": True}, {"bits": 12.5}, {"bits": 1e300},
                                    {"white_level": float("inf")}, {"gain": "x"}, {"bits": 10**400}])
def test_camera_from_dict_refuses_a_malformed_sensor(sensor: object) -> None:
    from svelive.core.camera import Camera

    with pytest.raises(SveliveError, match="camera sensor"):
        Camera.from_dict({"pattern": "1,4/16,64", "sensor": sensor})


def test_a_recording_whose_sensor_is_a_list(tmp_path: Path) -> None:
    import json

    from replay.container import FILE_HEADER, crc32, decode_header

    path = tmp_path / "r.sverec"
    out = run("record", "--source", "demo", "--cfa", "none", "--width", "64", "-o", path, "--frames", "2")
    assert out.returncode == 0, out.stderr
    data = bytearray(path.read_bytes())
    magic, version, length, _ = FILE_HEADER.unpack_from(data)
    meta = json.loads(bytes(data[FILE_HEADER.size:FILE_HEADER.size + length]))
    meta["camera"]["sensor"] = [12, 0]
    text = json.dumps(meta).encode()
    head = FILE_HEADER.pack(magic, version, len(text), crc32(text)) + text
    data[:len(head)] = head
    data[len(head):FILE_HEADER.size + length] = bytes(FILE_HEADER.size + length - len(head))
    path.write_bytes(bytes(data))
    decode_header(bytes(data[:4096]), str(path))  # the container itself is intact
    for verb in (["replay-info", path], ["export", path, "--png", tmp_path / "png"]):
        one_line_error(run(*verb), "sensor")


# ----- item 17: version, EXR attributes ----------------------------------------------------

def test_version() -> None:
    out = run("--version")
    assert out.returncode == 0 and out.stdout.strip() == f"svelive {svelive.__version__}"
    assert svelive.__version__[0].isdigit()


def test_reconstruct_writes_the_standard_exr_attributes(raw_png: Path, tmp_path: Path) -> None:
    from svelive.exr import STANDARD_ATTRIBUTES

    out = run("reconstruct", raw_png, "--pattern", "1,4/16,64", "--white-level", "4095", "-o", tmp_path / "h.exr")
    assert out.returncode == 0, out.stderr
    _, header = read_exr(tmp_path / "h.exr")
    assert {"units", "method", "pattern", "blackLevel", "whiteLevel", "svelive"} <= set(header)
    assert "unit" not in header and "svelive_method" not in header
    assert set(STANDARD_ATTRIBUTES) >= {"units", "method", "pattern", "cfa", "blackLevel", "whiteLevel", "frameId",
                                        "timestamp"}


def test_reconstruct_refuses_exposures_whose_values_float32_reconstruction_cannot_hold(raw_png: Path,
                                                                                       tmp_path: Path) -> None:
    # 0.0001 as the shortest exposure of a 12-bit reading: 4e7 DN at exposure 1, where the adaptive method's
    # float32 noise weights had already failed (a bright flat field came back 2^15 times too dark)
    out = run("reconstruct", raw_png, "--pattern", "0.0001,0.0004/0.0016,0.0064", "--bits", "12", "-o",
              tmp_path / "x.exr")
    one_line_error(out, "2^24", "--bits")
    assert run("reconstruct", raw_png, "--pattern", "0.001,0.004/0.016,0.064", "--bits", "12", "-o",
               tmp_path / "ok.exr").returncode == 0


def test_check_depth_at_its_limit() -> None:
    from svelive.core.pattern import MAX_VALUE, Pattern, check_depth

    check_depth(Pattern.parse(f"{4095 / MAX_VALUE!r},1"), 12)
    with pytest.raises(SveliveError, match="at least"):
        check_depth(Pattern.parse(f"{4095 / MAX_VALUE * 0.99!r},1"), 12)
    check_depth(Pattern.parse(f"1,{MAX_VALUE:.0f}"), 16)  # long exposures make values small: always fine
