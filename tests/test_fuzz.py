"""Property-based tests (hypothesis): untrusted input gives a result or a SveliveError, never another exception.

Three parsers of outside data: the exposure pattern's text form, the pixel-format
decoders (bytes from a camera), and the recording reader (a file on disk, damaged
at random). Each property runs a bounded number of examples (``max_examples``
below) so the whole file takes well under a minute; ``SVELIVE_FUZZ_EXAMPLES=N``
raises every bound to N for a longer search (docs/reliability.md).
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis", reason="the fuzz suite needs hypothesis (pip install -e .[test])")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st

from svelive.core import formats  # noqa: E402
from svelive.core.errors import SveliveError  # noqa: E402
from svelive.core.pattern import EXPOSURE_RANGE, MAX_RATIO, Pattern  # noqa: E402


def budget(n: int) -> settings:
    """Hypothesis settings of n examples (or SVELIVE_FUZZ_EXAMPLES), no per-example deadline (a loaded machine)."""
    n = int(os.environ.get("SVELIVE_FUZZ_EXAMPLES", n))
    return settings(max_examples=n, deadline=None, derandomize="SVELIVE_FUZZ_EXAMPLES" not in os.environ,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])


# ----- the pattern parser ------------------------------------------------------------------

NUMBERS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.floats(min_value=1e-40, max_value=1e40).map(lambda v: f"{v:g}"),
    st.integers(-10, 10**12).map(str),
    st.sampled_from(["", " ", "nan", "inf", "-0", "1e-300", "1e309", "0x10", "1_000", "١", "1/", "4,"]),
)
PATTERN_TEXT = st.one_of(
    st.text(max_size=40),
    st.text(alphabet="0123456789.,/ e-+", max_size=40),
    st.lists(st.lists(NUMBERS, min_size=1, max_size=5).map(",".join), min_size=1, max_size=5).map("/".join),
)


def check_pattern(pattern: Pattern) -> None:
    """What every Pattern the parser accepts guarantees."""
    tile = pattern.tile
    assert tile.ndim == 2 and tile.size > 0 and np.all(np.isfinite(tile))
    assert EXPOSURE_RANGE[0] <= tile.min() and tile.max() <= EXPOSURE_RANGE[1]
    assert pattern.ratio <= MAX_RATIO
    exposure = pattern.exposure_map((5, 7))
    assert exposure.dtype == np.float32 and np.all(exposure > 0) and np.all(np.isfinite(1 / exposure))
    assert Pattern.parse(str(pattern)).shape == pattern.shape  # the text form parses back


@budget(400)
@given(PATTERN_TEXT)
def test_pattern_parser_gives_a_pattern_or_a_one_line_error(text: str) -> None:
    try:
        pattern = Pattern.parse(text)
    except SveliveError as exc:
        assert "\n" not in str(exc)
        return
    check_pattern(pattern)


@budget(60)
@given(st.lists(st.lists(st.floats(min_value=2**-24, max_value=2**24), min_size=1, max_size=3), min_size=1,
                max_size=3).filter(lambda rows: len({len(r) for r in rows}) == 1),
       st.integers(1, 16))
def test_theory_of_any_accepted_pattern(rows: list[list[float]], bits: int) -> None:
    from svelive.core.pattern import dynamic_range_db, unique_levels

    text = "/".join(",".join(repr(v) for v in row) for row in rows)
    try:
        pattern = Pattern.parse(text)
    except SveliveError:
        assert max(map(max, rows)) / min(map(min, rows)) > MAX_RATIO
        return
    assert np.isfinite(dynamic_range_db(pattern, bits))
    try:
        q = unique_levels(pattern, bits)
    except SveliveError as exc:  # too many levels to enumerate: said in one line
        assert "enumerate" in str(exc)
        return
    assert 2**bits <= q <= len(pattern.levels) * 2**bits


# ----- the pixel-format decoders -----------------------------------------------------------

FORMAT_NAMES = sorted(formats.names())


@budget(300)
@given(data=st.binary(max_size=600), width=st.integers(-2, 40), height=st.integers(-2, 40),
       name=st.sampled_from(FORMAT_NAMES), stride=st.one_of(st.none(), st.integers(-4, 120)))
def test_decoders_give_a_frame_or_a_one_line_error(data: bytes, width: int, height: int, name: str,
                                                    stride: int | None) -> None:
    fmt = formats.lookup(name)
    try:
        out = formats.unpack(data, width, height, name, stride)
    except SveliveError as exc:
        assert "\n" not in str(exc)
        return
    assert out.shape == (height, width) and out.dtype == fmt.dtype
    if fmt.packing != "none":  # a packed value has exactly the format's bits (an unpacked 16-bit container
        assert int(out.max(initial=0)) < 2**fmt.bits  # passes on what the camera sent: above white is censored)


@budget(100)
@given(width=st.integers(1, 10**9), height=st.integers(1, 10**9), name=st.sampled_from(FORMAT_NAMES),
       stride=st.one_of(st.none(), st.integers(1, 10**10)))
def test_decoders_refuse_sizes_the_data_cannot_hold_without_allocating(width: int, height: int, name: str,
                                                                       stride: int | None) -> None:
    try:
        out = formats.unpack(b"\x00" * 64, width, height, name, stride)
    except SveliveError:
        return
    assert out.size <= 64 * 8 // formats.lookup(name).bits  # only what 64 bytes can hold


@budget(100)
@given(st.text(max_size=20))
def test_format_names_are_looked_up_or_refused(name: str) -> None:
    try:
        formats.lookup(name)
    except SveliveError as exc:
        assert "\n" not in str(exc)


# ----- image files (raw frames on disk) ----------------------------------------------------

@budget(120)
@given(kind=st.sampled_from(["pgm", "png", "tif"]), width=st.integers(0, 70000), height=st.integers(0, 70000),
       maxval=st.integers(0, 70000), body=st.binary(max_size=400))
def test_an_image_file_reads_or_gives_a_one_line_error(tmp_path_factory, kind: str, width: int, height: int,
                                                       maxval: int, body: bytes) -> None:
    """A header with any size and depth, then any bytes: a raw frame or a one-line error, never a crash or an
    allocation of what the header claims."""
    from svelive.cli.reconstruct import read_raw

    head = {"pgm": f"P5\n{width} {height}\n{maxval}\n".encode(),
            "png": b"\x89PNG\r\n\x1a\n\x00\x00\x00\x0dIHDR" + width.to_bytes(4, "big") + height.to_bytes(4, "big"),
            "tif": b"II*\x00\x08\x00\x00\x00"}[kind]
    path = tmp_path_factory.mktemp("img") / f"frame.{kind}"
    path.write_bytes(head + body)
    try:
        raw = read_raw(path)
    except SveliveError as exc:
        assert "\n" not in str(exc)
        return
    assert raw.ndim == 2 and raw.dtype in (np.uint8, np.uint16)


# ----- the recording reader ----------------------------------------------------------------

class Recording(tuple):
    """(file bytes, frames written); its repr is short, so a failing example's report stays readable."""

    def __repr__(self) -> str:
        return f"<recording of {len(self[0])} bytes, {len(self[1])} frames>"


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Recording:
    """A small closed recording (4 frames of 12x8 Mono12, dual-ISO-free mono camera) and its frames."""
    from replay.writer import RecordingWriter
    from svelive.core.camera import Camera
    from svelive.core.frame import Frame
    from svelive.core.sensor import Sensor

    path = tmp_path_factory.mktemp("fuzz") / "small.sverec"
    camera = Camera.build("1,4/16,64", sensor=Sensor(12, 64))
    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 4096, (8, 12)).astype(np.uint16) for _ in range(4)]
    with RecordingWriter(path, source="fuzz") as writer:
        for i, raw in enumerate(frames):
            writer.append(Frame(raw=raw, frame_id=i, host_time_ns=1000 * i, device_time_ns=None,
                                pixel_format="Mono12", camera=camera))
    return Recording((path.read_bytes(), frames))


def read_everything(path: Path, originals: list[np.ndarray]) -> int:
    """Open the recording and read every frame; returns how many were intact. Anything but a SveliveError
    (RecordingError and CorruptFrameError are) fails the test; an intact frame must be one that was written."""
    from replay.reader import RecordingReader

    known = {raw.tobytes() for raw in originals}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            reader = RecordingReader(path)
        except SveliveError as exc:
            assert "\n" not in str(exc)
            return 0
        with reader:
            reader.info()
            intact = 0
            for i in range(len(reader)):
                try:
                    frame = reader.read(i)
                except SveliveError as exc:
                    assert "\n" not in str(exc)
                    continue
                assert frame.raw.tobytes() in known and frame.raw.shape == originals[0].shape
                intact += 1
            return intact


DAMAGE = st.lists(st.one_of(
    st.tuples(st.just("flip"), st.integers(0, 10**6), st.integers(1, 255)),
    st.tuples(st.just("zero"), st.integers(0, 10**6), st.integers(1, 200)),
    st.tuples(st.just("truncate"), st.integers(0, 10**6), st.just(0)),
    st.tuples(st.just("append"), st.integers(0, 10**6), st.integers(1, 300)),
), min_size=1, max_size=4)


def damaged(data: bytes, damage: list[tuple[str, int, int]]) -> bytes:
    out = bytearray(data)
    for kind, where, value in damage:
        at = where % max(len(out), 1)
        if kind == "flip" and out:
            out[at] ^= value
        elif kind == "zero":
            out[at:at + value] = bytes(len(out[at:at + value]))
        elif kind == "truncate":
            del out[at:]
        elif kind == "append":
            out += bytes((at + k) % 256 for k in range(value))
    return bytes(out)


@budget(150)
@given(damage=DAMAGE)
def test_a_damaged_recording_gives_intact_frames_or_one_line_errors(recording, tmp_path: Path, damage) -> None:
    data, frames = recording
    path = tmp_path / "damaged.sverec"
    path.write_bytes(damaged(data, damage))
    read_everything(path, frames)


def test_the_undamaged_recording_reads_whole(recording, tmp_path: Path) -> None:
    data, frames = recording
    path = tmp_path / "whole.sverec"
    path.write_bytes(data)
    assert read_everything(path, frames) == len(frames)


JSON_VALUES = st.recursive(
    st.one_of(st.none(), st.booleans(), st.integers(-2**70, 2**70), st.floats(), st.text(max_size=12)),
    lambda inner: st.one_of(st.lists(inner, max_size=3), st.dictionaries(st.text(max_size=8), inner, max_size=3)),
    max_leaves=6,
)


@budget(200)
@given(key=st.sampled_from(["width", "height", "dtype", "pixel_format", "pattern", "sensor", "camera", "camera.sensor",
                            "camera.sensor.bits", "camera.sensor.white_level", "camera.pattern", "camera.cfa",
                            "camera.response", "camera.sensor.black_level", "format"]),
       value=JSON_VALUES)
def test_a_recording_with_any_header_value_opens_or_says_why(recording, tmp_path: Path, key: str, value) -> None:
    """The header's JSON replaced field by field with any JSON value, checksum recomputed: what a hand-edited
    or foreign file can hold."""
    from replay.container import FILE_HEADER, HEADER_ALIGN, encode_header

    data, frames = recording
    _, _, length, _ = FILE_HEADER.unpack_from(data)
    meta = json.loads(data[FILE_HEADER.size:FILE_HEADER.size + length])
    *parents, last = key.split(".")
    node = meta
    for part in parents:
        node = node[part]
    node[last] = value
    try:
        head = encode_header(meta)
    except ValueError:  # NaN and infinity are valid Python JSON; the writer never produces them, fine either way
        return
    old = FILE_HEADER.size + length
    old += -old % HEADER_ALIGN
    path = tmp_path / "edited.sverec"
    path.write_bytes(head + data[old:])
    read_everything(path, frames)
