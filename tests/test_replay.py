"""The recording container: round trip, seeking, timing, crash safety and bad input."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest

from replay import CorruptFrameError, RecordingError, RecordingReader, RecordingWriter
from replay.container import FOOTER, RECORD_HEADER
from svelive.capture import open_source
from svelive.cli import main
from svelive.core.camera import Camera
from svelive.core.errors import SveliveError
from svelive.core.frame import Frame
from svelive.core.sensor import Sensor

SENSOR = Sensor(bits=12, black_level=64)


def make_frames(n: int, h: int = 24, w: int = 32, dt_ms: float = 20.0) -> list[Frame]:
    rng = np.random.default_rng(1)
    return [Frame(raw=rng.integers(0, 4096, (h, w), dtype=np.uint16), frame_id=100 + i,
                  host_time_ns=int(1e9 + i * dt_ms * 1e6), device_time_ns=int(5e9 + i * dt_ms * 1e6),
                  pixel_format="Mono12", camera=Camera(sensor=SENSOR)) for i in range(n)]


def write(path: Path, frames: list[Frame], pattern: str = "1,4/16,64") -> None:
    with RecordingWriter(path, pattern=pattern, source="test") as w:
        for f in frames:
            w.append(f)


def test_round_trip_metadata_and_constant_time_seek(tmp_path: Path) -> None:
    frames = make_frames(12)
    path = tmp_path / "a.sverec"
    write(path, frames)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a clean file gives no warning
        r = RecordingReader(path)
    assert r.clean and len(r) == 12 and r.pattern == "1,4/16,64" and r.sensor == SENSOR
    for i in (7, 0, 11, -1, 3):  # any order
        got = r.read(i)
        want = frames[i]
        np.testing.assert_array_equal(got.raw, want.raw)
        assert (got.frame_id, got.host_time_ns, got.device_time_ns, got.pixel_format) == \
            (want.frame_id, want.host_time_ns, want.device_time_ns, "Mono12")
    info = r.info()
    assert info["frames"] == 12 and info["clock"] == "device" and info["duration_s"] == pytest.approx(0.22)
    with pytest.raises(RecordingError, match="out of range"):
        r.read(12)
    r.close()


def test_uint8_and_no_device_clock(tmp_path: Path) -> None:
    frames = [Frame(raw=np.full((5, 7), i, np.uint8), frame_id=i, host_time_ns=i * 10**9, pixel_format="Mono8",
                    camera=Camera(sensor=Sensor(bits=8))) for i in range(3)]
    write(tmp_path / "b.sverec", frames, pattern=None)
    with RecordingReader(tmp_path / "b.sverec") as r:
        assert r.read(2).raw.dtype == np.uint8 and r.read(2).raw[0, 0] == 2 and r.read(1).device_time_ns is None
        assert r.clock == "host" and r.duration_s == 2.0 and r.pattern is None


def test_replay_source_timing_speed_and_loop(tmp_path: Path) -> None:
    path = tmp_path / "t.sverec"
    write(path, make_frames(6, dt_ms=40))
    with open_source(f"replay:{path}") as s:  # recorded timing: 5 intervals of 40 ms
        t = time.monotonic()
        got = list(s.frames(seconds=5))
        recorded_pace = time.monotonic() - t
        assert len(got) == 6 and 0.18 < recorded_pace < 2  # waits the 0.2 s; the upper bound only catches hangs
        assert s.pattern == "1,4/16,64" and s.stats()["state"] == "ended"
    with open_source(f"replay:{path}", speed=4.0) as s:
        t = time.monotonic()
        assert len(list(s)) == 6
        assert time.monotonic() - t < recorded_pace / 2  # 1/4 of the time expected; a ratio, robust to load
    with open_source(f"replay:{path}", speed=0, loop=True, start=4) as s:
        ids = [f.frame_id for f in s.frames(limit=9)]
    assert ids == [104, 105, 106, 107, 108, 109, 110, 111, 112]  # ids keep increasing over loops


def test_torn_and_damaged_frames(tmp_path: Path) -> None:
    path = tmp_path / "c.sverec"
    frames = make_frames(5)
    write(path, frames)
    data = path.read_bytes()
    with RecordingReader(path) as r:
        record, start = r.layout.record_size, r.layout.data_offset
    # a recorder killed mid-frame: no index, last record cut short
    (tmp_path / "torn.sverec").write_bytes(data[: start + 3 * record + record // 2])
    with pytest.warns(UserWarning, match="torn last frame"):
        r = RecordingReader(tmp_path / "torn.sverec")
    assert len(r) == 3 and not r.clean
    np.testing.assert_array_equal(r.read(2).raw, frames[2].raw)
    r.close()
    # a complete-length last record whose payload was not fully written
    bad = bytearray(data[: start + 4 * record])
    bad[start + 3 * record + RECORD_HEADER.size + 100] ^= 0xFF
    (tmp_path / "torn2.sverec").write_bytes(bad)
    with pytest.warns(UserWarning, match="checksum mismatch"), RecordingReader(tmp_path / "torn2.sverec") as r2:
        assert len(r2) == 3
    # damage inside an indexed file: that frame raises, the replay source skips it and counts it
    bad = bytearray(data)
    bad[start + 1 * record + RECORD_HEADER.size + 5] ^= 0x01
    (tmp_path / "rot.sverec").write_bytes(bad)
    with RecordingReader(tmp_path / "rot.sverec") as r, pytest.raises(CorruptFrameError, match="frame 1 checksum"):
        r.read(1)
    with pytest.warns(UserWarning, match="frame 1 checksum"), open_source(f"replay:{tmp_path / 'rot.sverec'}",
                                                                        speed=0) as s:
        assert [f.frame_id for f in s] == [100, 102, 103, 104] and s.stats()["drops"] == {"checksum": 1}


def test_corrupt_index_is_rebuilt(tmp_path: Path) -> None:
    path = tmp_path / "d.sverec"
    write(path, make_frames(4))
    data = bytearray(path.read_bytes())
    data[-FOOTER.size - 10] ^= 0xFF  # inside the index table
    path.write_bytes(data)
    with pytest.warns(UserWarning, match="corrupt index"):
        r = RecordingReader(path)
    assert len(r) == 4 and r.read(3).frame_id == 103
    r.close()
    data[-16] ^= 0xFF  # and the footer's index offset too
    path.write_bytes(data)
    with pytest.warns(UserWarning, match="corrupt index footer"), RecordingReader(path) as r:
        assert len(r) == 4


def test_bad_files_give_one_line_errors(tmp_path: Path) -> None:
    path = tmp_path / "e.sverec"
    write(path, make_frames(2))
    data = path.read_bytes()
    cases = {
        "magic": (b"GARBAGE!" + data[8:], "not an svelive recording"),
        "short": (data[:10], "too short|truncated"),
        "header": (data[:40] + bytes([data[40] ^ 1]) + data[41:], "header checksum"),
        "empty": (b"", "too short"),
    }
    for name, (blob, message) in cases.items():
        p = tmp_path / f"{name}.sverec"
        p.write_bytes(blob)
        with pytest.raises(RecordingError, match=message):
            RecordingReader(p)
    with pytest.raises(RecordingError, match="is a directory"):
        RecordingReader(tmp_path)
    with pytest.raises(RecordingError, match="no such recording"):
        RecordingReader(tmp_path / "missing.sverec")
    # unknown pixel format in a (validly checksummed) header
    from replay.container import encode_header

    head = encode_header({"width": 4, "height": 2, "dtype": "uint16", "pixel_format": "Weird42"})
    (tmp_path / "fmt.sverec").write_bytes(head)
    with pytest.raises(RecordingError, match="unknown pixel format 'Weird42'"):
        RecordingReader(tmp_path / "fmt.sverec")


def test_writer_refuses_changing_frames_and_keeps_what_it_has(tmp_path: Path) -> None:
    path = tmp_path / "f.sverec"
    frames = make_frames(3)
    with RecordingWriter(path) as w:
        w.append(frames[0])
        w.append(frames[1])
        with pytest.raises(RecordingError, match="is 16x8 uint16 but the recording is 32x24"):
            w.append(Frame(raw=np.zeros((8, 16), np.uint16), frame_id=9, host_time_ns=0, pixel_format="Mono12"))
        with pytest.raises(RecordingError, match="is Mono16 but the recording is Mono12"):
            w.append(Frame(raw=frames[2].raw, frame_id=9, host_time_ns=0, pixel_format="Mono16"))
    with RecordingReader(path) as r:
        assert len(r) == 2
    with pytest.raises(RecordingError, match="already exists"):
        RecordingWriter(path)
    with pytest.raises(RecordingError, match="is a directory"):
        RecordingWriter(tmp_path)
    with pytest.raises(RecordingError, match="does not exist"):
        RecordingWriter(tmp_path / "no" / "x.sverec")
    RecordingWriter(tmp_path / "none.sverec").close()
    assert not (tmp_path / "none.sverec").exists()  # no frame, no file


def test_kill_9_mid_recording_keeps_every_complete_frame(tmp_path: Path) -> None:
    out = tmp_path / "killed.sverec"
    cmd = [sys.executable, "-m", "svelive.cli", "record", "--source", "demo", "--width", "320", "--height", "240",
           "--fps", "100", "-o", str(out)]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and (not out.exists() or out.stat().st_size < 40 * 160_000):
            time.sleep(0.05)
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
    assert proc.returncode == -signal.SIGKILL
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        r = RecordingReader(out)
    assert not r.clean and any("not closed cleanly" in str(w.message) for w in caught)
    n = len(r)
    assert n >= 35
    size = out.stat().st_size
    assert n == (size - r.layout.data_offset) // r.layout.record_size or \
        n == (size - r.layout.data_offset) // r.layout.record_size - 1  # a torn last one is dropped
    ids = [r.read(i).frame_id for i in range(n)]  # every kept frame reads back with a valid checksum
    assert ids == list(range(n))
    r.close()
    assert main(["replay-info", str(out)]) == 0


def test_cli_record_replay_info_export(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rec = tmp_path / "r.sverec"
    assert main(["record", "--source", "demo", "--cfa", "none", "--width", "64", "--height", "48", "--fps", "0",
                 "--frames", "5", "-o", str(rec)]) == 0
    capsys.readouterr()
    assert main(["replay-info", str(rec)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["frames"] == 5 and info["pattern"] == "1,4/16,64" and info["pixel_format"] == "Mono12"
    assert main(["export", str(rec), "--png", str(tmp_path / "png")]) == 0
    assert sorted(p.name for p in (tmp_path / "png").iterdir())[:2] == ["frame_000000.png", "frame_000001.png"]
    # import the exported sequence back: same pixels
    rec2 = tmp_path / "r2.sverec"
    assert main(["record", "--source", f"images:{tmp_path / 'png'}", "--pattern", "1,4/16,64", "--bits", "12",
                 "-o", str(rec2)]) == 0
    with RecordingReader(rec) as a, RecordingReader(rec2) as b:
        assert len(b) == 5 and b.sensor.bits == 12
        for i in range(5):
            np.testing.assert_array_equal(a.read(i).raw, b.read(i).raw)
    capsys.readouterr()
    assert main(["replay-info", str(tmp_path)]) == 2
    assert "is a directory" in capsys.readouterr().err


def test_writer_refuses_unknown_pixel_format(tmp_path: Path) -> None:
    with RecordingWriter(tmp_path / "u.sverec") as w, pytest.raises(RecordingError, match="unknown pixel format"):
        w.append(Frame(raw=np.zeros((2, 2), np.uint8), frame_id=0, host_time_ns=0, pixel_format="Weird42"))
    assert not (tmp_path / "u.sverec").exists()


# ----- colour: the camera in the header ---------------------------------------------------------


def test_header_stores_the_camera_and_the_reader_restores_it(tmp_path: Path) -> None:
    from svelive.core.response import Response

    response = Response(coefficients=(0.0, 0.7, 0.3), black_level=64, white_level=4095)
    camera = Camera.build("dual-iso", sensor=Sensor(bits=12, black_level=64, gain=2.5, read_noise=1.5),
                          response=response)
    frames = [Frame(raw=np.full((8, 12), 100 + i, np.uint16), frame_id=i, host_time_ns=i * 10**6,
                    pixel_format="BayerRG12", camera=camera) for i in range(3)]
    path = tmp_path / "colour.sverec"
    with RecordingWriter(path, source="test") as w:
        for f in frames:
            w.append(f)
    with RecordingReader(path) as r:
        assert r.meta["camera"]["cfa"] == "R,G/G,B" and r.meta["camera"]["pattern"] == "1/1/8/8"
        assert r.camera.cfa.name == "RGGB" and str(r.camera.pattern) == "1/1/8/8"
        assert r.camera.sensor == camera.sensor and r.camera.response == response
        assert r.read(2).camera == r.camera and r.info()["cfa"] == "RGGB"
    # a replay delivers frames with that camera; a monochrome reading of Bayer frames is refused
    with open_source(f"replay:{path}", speed=0) as s:
        got = list(s)
    assert len(got) == 3 and all(f.camera.cfa.name == "RGGB" and f.camera.response == response for f in got)
    with pytest.raises(SveliveError, match="cannot be reconstructed as monochrome: drop --cfa none"):
        open_source(f"replay:{path}", cfa="none").open()
    with open_source(f"replay:{path}", speed=0, pattern="1/8/1/8") as s:  # another exposure pattern, same filter
        frame = s.read()
    assert str(frame.camera.pattern) == "1/8/1/8" and frame.camera.cfa.name == "RGGB"


def test_old_header_with_a_bayer_format_still_gives_the_colour_filter(tmp_path: Path) -> None:
    from replay.container import encode_header

    meta = {"width": 4, "height": 2, "dtype": "uint16", "pixel_format": "BayerGB12", "pattern": "1,4/16,64",
            "sensor": {"bits": 12, "black_level": 10.0}}
    (tmp_path / "old.sverec").write_bytes(encode_header(meta))
    with RecordingReader(tmp_path / "old.sverec") as r:
        assert r.camera.cfa.name == "GBRG" and str(r.camera.pattern) == "1,4/16,64" and r.sensor.black_level == 10
        assert r.info()["cfa"] == "GBRG"
    (tmp_path / "mono.sverec").write_bytes(encode_header({**meta, "pixel_format": "Mono12"}))
    with RecordingReader(tmp_path / "mono.sverec") as r:
        assert r.camera.cfa is None and r.info()["cfa"] is None


@pytest.mark.parametrize("camera, message", [
    ({"pattern": "1/1/8/8", "cfa": "RGGB", "sensor": [12, 0]}, "camera sensor must be a JSON object"),
    ({"pattern": "1/1/8/8", "cfa": "RGGB", "sensor": {"bits": "twelve"}}, "camera sensor is invalid"),
    ({"pattern": "1/1/8/8", "cfa": "RGBX"}, "RGBX"),
    ({"pattern": "1/1/8/8", "cfa": "RGGB", "response": {"domain": [0, 1]}}, "response data"),
    ([], "must be a JSON object"),
    ("RGGB", "must be a JSON object"),
    ({"pattern": "1/1/8/8", "cfa": None}, "colour filter none but the frames are BayerRG12"),
    ({"pattern": "1/1/8/8", "cfa": "GRBG"}, "colour filter GRBG but the frames are BayerRG12"),
])
def test_malformed_camera_in_the_header_is_a_one_line_error(tmp_path: Path, camera: object, message: str) -> None:
    from replay.container import encode_header

    meta = {"width": 4, "height": 2, "dtype": "uint16", "pixel_format": "BayerRG12", "camera": camera}
    (tmp_path / "bad.sverec").write_bytes(encode_header(meta))
    with pytest.raises(RecordingError, match=message) as info:
        RecordingReader(tmp_path / "bad.sverec")
    assert "\n" not in str(info.value)


def test_writer_takes_the_bayer_format_filter_and_refuses_a_contradiction(tmp_path: Path) -> None:
    raw = np.zeros((4, 6), np.uint8)
    with RecordingWriter(tmp_path / "a.sverec") as w:  # a hand-made frame: its camera knows no filter
        w.append(Frame(raw=raw, frame_id=0, host_time_ns=0, pixel_format="BayerBG8"))
    with RecordingReader(tmp_path / "a.sverec") as r:
        assert r.camera.cfa.name == "BGGR"
    with RecordingWriter(tmp_path / "b.sverec") as w, pytest.raises(RecordingError, match="its camera says RGGB"):
        w.append(Frame(raw=raw, frame_id=0, host_time_ns=0, pixel_format="BayerBG8", camera=Camera.build(cfa="RGGB")))
    assert not (tmp_path / "b.sverec").exists()


def test_cli_record_takes_cfa_and_replay_info_shows_it(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rec = tmp_path / "c.sverec"
    assert main(["record", "--source", "demo", "--width", "64", "--height", "48", "--fps", "0", "--frames", "3",
                 "-o", str(rec)]) == 0  # the colour demo
    capsys.readouterr()
    assert main(["replay-info", str(rec)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["cfa"] == "RGGB" and info["pixel_format"] == "BayerRG12" and info["pattern"] == "1/1/8/8"
    # an image sequence is whatever --cfa says; its frames then carry the Bayer name of their container
    assert main(["export", str(rec), "--png", str(tmp_path / "png")]) == 0
    rec2 = tmp_path / "c2.sverec"
    assert main(["record", "--source", f"images:{tmp_path / 'png'}", "--pattern", "dual-iso", "--bits", "12",
                 "-o", str(rec2)]) == 0
    capsys.readouterr()
    assert main(["replay-info", str(rec2)]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["cfa"] == "RGGB" and info["pixel_format"] == "BayerRG16" and info["pattern"] == "1/1/8/8"
    rec3 = tmp_path / "c3.sverec"
    assert main(["record", "--source", f"images:{tmp_path / 'png'}", "--pattern", "1/1/8/8", "--cfa", "GRBG",
                 "-o", str(rec3)]) == 0
    with RecordingReader(rec3) as r:
        assert r.camera.cfa.name == "GRBG" and r.pixel_format == "BayerGR16"
    # refusals are one line on stderr, exit 2
    capsys.readouterr()
    assert main(["record", "--source", f"replay:{rec}", "--cfa", "none", "-o", str(tmp_path / "x.sverec")]) == 2
    assert "cannot be reconstructed as monochrome" in capsys.readouterr().err
    assert main(["record", "--source", "demo", "--cfa", "RGBX", "-o", str(tmp_path / "y.sverec")]) == 2
    err = capsys.readouterr().err
    assert "'RGBX'" in err and err.count("\n") == 1


@pytest.mark.parametrize("case", ["missing", "directory", "empty", "garbage", "no frames"])
def test_a_replay_source_that_can_never_work_fails_when_built(tmp_path: Path, case: str) -> None:
    """serve builds its source once at start-up: a recording that can never play must fail there, in one line."""
    path = tmp_path / "x.sverec"
    if case == "directory":
        path = tmp_path
    elif case == "empty":
        path.write_bytes(b"")
    elif case == "garbage":
        path.write_bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    elif case == "no frames":
        from replay.container import encode_header

        path.write_bytes(encode_header({"width": 4, "height": 2, "dtype": "uint16", "pixel_format": "Mono12"}))
    with pytest.raises(SveliveError) as info:
        open_source(f"replay:{path}")
    assert "\n" not in str(info.value) and str(path) in str(info.value)


def test_replay_source_takes_sensor_levels_over_the_recorded_ones(tmp_path: Path) -> None:
    path = tmp_path / "levels.sverec"
    write(path, make_frames(2))
    with open_source(f"replay:{path}", speed=0) as s:
        assert next(iter(s)).camera.sensor.black_level == 64
    source = open_source(f"replay:{path}", speed=0, black_level=10, white_level=4000)
    assert source.camera.sensor.black_level == 10  # known when built, before it is opened
    with source:
        sensor = next(iter(source)).camera.sensor
    assert (sensor.black_level, sensor.white_level, sensor.bits) == (10, 4000, 12)


def test_export_skips_and_counts_a_damaged_frame(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "f.sverec"
    frames = make_frames(20)
    write(path, frames)
    with RecordingReader(path) as r:
        start = r.layout.data_offset
    data = bytearray(path.read_bytes())
    data[start + RECORD_HEADER.size + 7] ^= 0x10  # one flipped bit in frame 0's pixels
    path.write_bytes(data)
    out = tmp_path / "png"
    assert main(["export", str(path), "--png", str(out), "-q"]) == 0
    names = sorted(p.name for p in out.iterdir())
    assert len(names) == 19 and names[0] == "frame_000001.png"
    assert "1 damaged frames skipped: 0" in capsys.readouterr().err
    from svelive.cli.reconstruct import read_raw

    np.testing.assert_array_equal(read_raw(out / "frame_000019.png"), frames[19].raw)


def test_rebuilt_index_recovers_every_intact_frame_past_a_damaged_header(tmp_path: Path) -> None:
    path = tmp_path / "g.sverec"
    frames = make_frames(6)
    write(path, frames)
    with RecordingReader(path) as r:
        record, start, end = r.layout.record_size, r.layout.data_offset, r.layout.data_offset + 6 * r.layout.record_size
    data = bytearray(path.read_bytes()[:end])  # killed before the index was written
    data[start + 2 * record + 20] ^= 0x01  # frame 2's record header (its frame id)
    path.write_bytes(data)
    with pytest.warns(UserWarning, match=r"1 damaged record\(s\) skipped \(2\); kept the 5 intact frames"):
        r = RecordingReader(path)
    with r:
        assert len(r) == 6 and r.damaged == (2,) and r.info()["damaged_records"] == [2]
        for i in (0, 1, 3, 4, 5):
            np.testing.assert_array_equal(r.read(i).raw, frames[i].raw)
            assert r.read(i).frame_id == 100 + i
        with pytest.raises(CorruptFrameError, match="frame 2"):
            r.read(2)
        assert np.all(np.diff(r.timeline_ns()) >= 0) and r.clock == "device"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with open_source(f"replay:{path}", speed=0) as s:
            assert [f.frame_id for f in s] == [100, 101, 103, 104, 105] and s.stats()["drops"] == {"checksum": 1}


def test_rebuilt_index_stops_at_an_index_without_footer(tmp_path: Path) -> None:
    """A close cut short after the index but before the footer: the index's bytes are no damaged frames."""
    path = tmp_path / "h.sverec"
    frames = [Frame(raw=np.full((4, 4), i, np.uint8), frame_id=i, host_time_ns=i, pixel_format="Mono8")
              for i in range(40)]
    write(path, frames, pattern="1,4/16,64")
    path.write_bytes(path.read_bytes()[:-FOOTER.size])
    with RecordingReader(path, warn=False) as r:
        assert len(r) == 40 and r.damaged == ()
        assert not any("damaged" in w or "torn" in w for w in r.warnings), r.warnings


def test_replay_info_verify_checks_every_payload(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "v.sverec"
    write(path, make_frames(5))
    assert main(["replay-info", str(path), "--verify", "-q"]) == 0
    assert json.loads(capsys.readouterr().out)["verified"] == {"frames": 5, "intact": 5, "damaged": []}
    with RecordingReader(path) as r:
        offset = r.layout.data_offset + 3 * r.layout.record_size + RECORD_HEADER.size + 11
    data = bytearray(path.read_bytes())
    data[offset] ^= 0x04
    path.write_bytes(data)
    assert main(["replay-info", str(path), "--verify", "-q"]) == 1
    assert json.loads(capsys.readouterr().out)["verified"] == {"frames": 5, "intact": 4, "damaged": [3]}


def test_record_overwrite_never_replaces_a_fifo_or_a_link(tmp_path):
    import os
    import subprocess
    import sys

    fifo, target, link = tmp_path / "fifo", tmp_path / "target.sverec", tmp_path / "link.sverec"
    os.mkfifo(fifo)
    target.write_bytes(b"keep me")
    link.symlink_to(target)
    for path in (fifo, link):
        out = subprocess.run([sys.executable, "-m", "svelive.cli", "record", "--source", "demo", "-o", str(path),
                              "--frames", "1", "--overwrite", "-q"], capture_output=True, text=True, timeout=120)
        assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1, out.stderr
    assert fifo.is_fifo() and link.is_symlink() and target.read_bytes() == b"keep me"


# ----- recorded exposure times: a replay with exposure control (issue 14) -------------------------------

def write_exposures(path: Path, frames: list[Frame], times: list[float | None]) -> None:
    with RecordingWriter(path, pattern="1,4/16,64", source="test") as w:
        for f, t in zip(frames, times):
            w.append(f, exposure_time=t)


def test_exposure_times_round_trip_and_old_recordings_have_none(tmp_path: Path) -> None:
    frames = make_frames(6)
    times = [1000.0, 1000.0, 1500.5, None, 1500.5, 2250.0]
    write_exposures(tmp_path / "e.sverec", frames, times)
    with RecordingReader(tmp_path / "e.sverec") as r:
        got = r.exposure_times()
        assert np.isnan(got[3]) and list(got[[0, 1, 2, 4, 5]]) == [1000.0, 1000.0, 1500.5, 1500.5, 2250.0]
        assert r.info()["exposure_times"] == [[1000.0, 2], [1500.5, 2], [2250.0, 1]]
        np.testing.assert_array_equal(r.read(2).raw, frames[2].raw)  # the pixels are untouched
    # a recording written without them (the bytes were zero before the field existed) has none
    write(tmp_path / "plain.sverec", frames)
    with RecordingReader(tmp_path / "plain.sverec") as r:
        assert np.isnan(r.exposure_times()).all() and r.info()["exposure_times"] is None
    # the field is inside the record header's checksum, in bytes an older reader skips: its layout of the
    # other fields is unchanged (the reader of before unpacked "<4sIqqqqII16x")
    import struct
    import zlib

    data = (tmp_path / "e.sverec").read_bytes()
    with RecordingReader(tmp_path / "e.sverec") as r:
        start, record = r.layout.data_offset, r.layout.record_size
    head = data[start + 2 * record: start + 2 * record + 64]
    old = struct.unpack("<4sIqqqqII16x", head)
    assert old[0] == b"SVFR" and old[2] == 2 and old[3] == frames[2].frame_id
    assert zlib.crc32(head[8:]) == old[1]
    assert struct.unpack_from("<d", head, 48)[0] == 1500.5
    # a damaged exposure field is a damaged record header, found by the checksum
    bad = bytearray(data)
    bad[start + 5 * record + 50] ^= 0x01
    (tmp_path / "bad.sverec").write_bytes(bytes(bad))
    with RecordingReader(tmp_path / "bad.sverec", warn=False) as r:
        assert np.isnan(r.exposure_times()[5])
        with pytest.raises(CorruptFrameError):
            r.read(5)
    with RecordingWriter(tmp_path / "x.sverec") as w, pytest.raises(RecordingError, match="positive"):
        w.append(frames[0], exposure_time=-3.0)


def test_replay_source_sets_its_exposure_by_playing_the_frames_recorded_at_it(tmp_path: Path) -> None:
    frames = make_frames(12, dt_ms=10)
    # three runs of four frames, as a sweep recorded from a camera would be
    times = [1000.0] * 4 + [1500.0] * 4 + [2250.0] * 4
    path = tmp_path / "sweep.sverec"
    write_exposures(path, frames, times)
    with open_source(f"replay:{path}", speed=0) as s:
        first = s.read()
        assert first.frame_id == 100 and s.exposure_time() == 1000.0  # the frame played last
        ids = [first.frame_id]
        for asked, picked in ((1500.0, 1500.0), (2240.0, 2250.0), (1000.0, 1000.0)):  # 2240: the camera rounds
            assert s.set_exposure_time(asked) == picked and s.exposure_time() == picked
            got = [s.read() for _ in range(7)]
            ids += [f.frame_id for f in got]
            # the recorded frames at that time, less the first of the run, over and over
            recorded = [(f.frame_id - 100) % 12 for f in got]
            run = [i for i, t in enumerate(times) if t == picked][1:]
            assert recorded == (run * 3)[:7], (picked, recorded)
            for f in got:
                np.testing.assert_array_equal(f.raw, frames[(f.frame_id - 100) % 12].raw)
        assert ids == sorted(ids) and len(set(ids)) == len(ids)  # ids keep increasing across choices and cycles
        assert s.stats()["exposure_time"] == 1000.0
        with pytest.raises(SveliveError, match="no frame was recorded at exposure time 5000 .*1000, 1500, 2250"):
            s.set_exposure_time(5000)
        assert s.exposure_time() == 1000.0  # a refused time changes nothing
    # a recording without exposure times: no exposure control
    write(tmp_path / "plain.sverec", frames)
    with open_source(f"replay:{tmp_path / 'plain.sverec'}", speed=0) as s:
        assert s.exposure_time() is None
        with pytest.raises(SveliveError, match="cannot set its exposure time"):
            s.set_exposure_time(1000)


def test_replay_chosen_exposure_plays_at_the_recorded_rate(tmp_path: Path) -> None:
    frames = make_frames(6, dt_ms=50)  # 20 fps recorded
    write_exposures(tmp_path / "r.sverec", frames, [1000.0, 1000.0, 1000.0, 2000.0, 2000.0, 2000.0])
    with open_source(f"replay:{tmp_path / 'r.sverec'}") as s:
        s.set_exposure_time(2000.0)
        t = time.monotonic()
        got = list(s.frames(limit=5, seconds=10))
        elapsed = time.monotonic() - t
        assert len(got) == 5 and elapsed >= 0.19  # 4 intervals of 50 ms at least; no upper bound (loaded machine)
        assert {(f.frame_id - 100) % 6 for f in got} == {4, 5}


def test_a_frames_exposure_time_is_recorded_and_read_back_with_it(tmp_path: Path) -> None:
    """A frame that carries its exposure time (a source stamping it) needs no argument to append."""
    import dataclasses

    frames = make_frames(3)
    with RecordingWriter(tmp_path / "t.sverec", pattern="1,4/16,64") as w:
        w.append(dataclasses.replace(frames[0], exposure_time=800.0))
        w.append(frames[1])  # none
        w.append(dataclasses.replace(frames[2], exposure_time=800.0), exposure_time=1200.0)  # the argument wins
    with RecordingReader(tmp_path / "t.sverec") as r:
        got = r.exposure_times()
        assert got[0] == 800.0 and np.isnan(got[1]) and got[2] == 1200.0
        assert [r.read(i).exposure_time for i in range(3)] == [800.0, None, 1200.0]


def test_demo_frames_carry_their_exposure_time(tmp_path: Path) -> None:
    with open_source("demo", width=64, height=48, fps=0, cfa="none", exposure_us=5000) as source:
        frame = next(iter(source))
        assert frame.exposure_time == 5000.0
        assert source.set_exposure_time(7500.0) == 7500.0
        assert next(iter(source)).exposure_time == 7500.0


def test_a_rebuilt_replay_source_resumes_after_the_last_frame_delivered(tmp_path: Path) -> None:
    path = tmp_path / "r.sverec"
    write(path, make_frames(6))  # ids 100..105
    with open_source(f"replay:{path}", speed=0, loop=True) as s:
        first = list(s.frames(limit=8))
    assert [f.frame_id for f in first] == list(range(100, 108))  # into the second loop
    with open_source(f"replay:{path}", speed=0, loop=True) as s:
        s.resume_after(first[-1])
        after = list(s.frames(limit=3))
    assert [f.frame_id for f in after] == [108, 109, 110]
    np.testing.assert_array_equal(after[0].raw, first[2].raw)  # recorded frame 2 again, in loop 2
    with open_source(f"replay:{path}", speed=0, loop=True) as s:  # not a frame of this recording: from the start
        s.resume_after(replace_id(first[0], 7))
        assert next(iter(s)).frame_id == 100
    with open_source(f"replay:{path}", speed=0) as s:  # after the last frame of a replay without loop: ended
        s.resume_after(first[5])
        assert list(s) == [] and s.stats()["state"] == "ended"


def replace_id(frame: Frame, frame_id: int) -> Frame:
    return dataclasses.replace(frame, frame_id=frame_id)


def test_the_service_reopens_a_failed_replay_where_it_stopped(tmp_path: Path) -> None:
    """A read that fails mid-replay (an I/O error) makes the capture stage rebuild the source; the
    replay goes on after the last frame delivered, not again from its start."""
    import threading

    from service.pipeline.capture import CaptureStage
    from service.pipeline.config import PipelineConfig
    from service.pipeline.handoff import NewestSlot
    from service.pipeline.meters import DropCounter
    from svelive.capture.replay import ReplaySource

    path = tmp_path / "f.sverec"
    write(path, make_frames(6, dt_ms=30))
    failed: list[int] = []

    class FailsOnce(ReplaySource):
        def _deliver_index(self, reader, i):
            if i == 3 and not failed:
                failed.append(i)
                raise OSError("read error (injected)")
            return super()._deliver_index(reader, i)

    config = PipelineConfig(source=f"replay:{path}", queue=8, retry_s=0.05)
    slot, stop = NewestSlot(config.queue), threading.Event()
    stage = CaptureStage(config, lambda: FailsOnce(config.source, str(path)), slot, DropCounter(), stop)
    thread = threading.Thread(target=stage.run, daemon=True)
    thread.start()
    ids: list[int] = []
    deadline = time.monotonic() + 20
    while stage.state != "ended" and time.monotonic() < deadline:
        frame = slot.get(0.05)
        if frame is not None:
            ids.append(frame.frame_id)
    while (frame := slot.get(0.01)) is not None:
        ids.append(frame.frame_id)
    stop.set()
    thread.join(5)
    assert failed == [3] and stage.reconnects() == 1
    assert ids == [100, 101, 102, 103, 104, 105]  # before: 100, 101, 102, then 100 ... 105 again
