"""Issue 28.1: RTSP pictures a recorder can use. A real ``svelive serve --rtsp`` (subprocess, loopback ports,
the still monochrome demo) and a real client (ffmpeg, RTP over TCP): 20 fresh connections of 60 frames each,
each must begin with a key frame carrying its SPS and PPS, decode without a single decoder complaint, have
strictly increasing time stamps, and show whole pictures, each compared with ``/snapshot.jpg``.

Before the fix every client's key frames came as one picture per slice (the payloader put SPS/PPS before
every slice: "concealing ... errors in I frame", the lower part a smear) and frames shared time stamps
("non monotonically increasing dts"). Clients that join a stream another client plays (one shared encoding)
must also begin with a key frame with SPS and PPS, and a burst of them must not make every frame a key frame."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest

from tests.test_service_helpers import free_port, stop_process

pytestmark = pytest.mark.skipif(shutil.which("ffmpeg") is None, reason="ffmpeg (the RTSP client) not installed")

WIDTH, HEIGHT, FRAMES, CLIENTS = 320, 192, 60, 20
#: what ffmpeg says of a picture it could not decode whole, or of time stamps out of order
COMPLAINTS = re.compile(r"corrupt|conceal|error|missing|non.monoton|invalid|no frame|decode_slice", re.IGNORECASE)


@pytest.fixture(scope="module")
def service():
    """``svelive serve`` on two free loopback ports, a still scene, RTSP on; yields (http_url, rtsp_url)."""
    http_port, rtsp_port = free_port(), free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "svelive.cli", "serve", "--source", "demo", "--cfa", "none",
         "--source-option", f"width={WIDTH}", "--source-option", f"height={HEIGHT}",
         "--source-option", "period_s=0", "--source-option", "fps=25",
         "--port", str(http_port), "--rtsp", str(rtsp_port)],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    url = f"http://127.0.0.1:{http_port}"
    try:
        deadline = time.monotonic() + 300  # a first run on a machine compiles the kernels
        while True:
            assert proc.poll() is None, f"serve exited: {proc.stderr.read()}"
            try:
                if httpx.get(url + "/api/state", timeout=2).json()["frames"]["reconstructed"] >= 10:
                    break
            except (httpx.HTTPError, KeyError, IndexError, TypeError):
                pass
            assert time.monotonic() < deadline, "serve did not reconstruct 10 frames in 300 s"
            time.sleep(0.5)
        yield url, f"rtsp://127.0.0.1:{rtsp_port}/live"
    finally:
        stop_process(proc)


def nal_types(annex_b: bytes) -> list[int]:
    """The NAL unit types of an H.264 Annex B byte stream, in order."""
    return [annex_b[m.end()] & 31 for m in re.finditer(b"\x00\x00\x01", annex_b) if m.end() < len(annex_b)]


def packets(framecrc: str) -> list[tuple[int, bool]]:
    """(dts, key frame) of each packet of ffmpeg's framecrc output."""
    out = []
    for line in framecrc.splitlines():
        if line.startswith("#") or not line.strip():
            continue
        fields = [f.strip() for f in line.split(",")]
        out.append((int(fields[1]), not any(f.startswith("F=") for f in fields[6:])))
    return out


def one_client(rtsp_url: str, tmp: Path) -> tuple[list[np.ndarray], list[tuple[int, bool]], bytes, str]:
    """One fresh ffmpeg connection: FRAMES decoded BGR pictures, the packets' (dts, key), the first packet's
    bytes as received (``-copyinkf``: ffmpeg's stream copy would drop packets before the first key frame), and
    what ffmpeg printed."""
    crc, first = tmp / "packets.crc", tmp / "first.h264"
    done = subprocess.run(
        ["ffmpeg", "-nostdin", "-hide_banner", "-loglevel", "warning", "-rtsp_transport", "tcp", "-i", rtsp_url,
         "-map", "0:v", "-frames:v", str(FRAMES), "-c", "copy", "-copyinkf", "-f", "framecrc", "-y", str(crc),
         "-map", "0:v", "-frames:v", "1", "-c", "copy", "-copyinkf", "-f", "h264", "-y", str(first),
         "-map", "0:v", "-frames:v", str(FRAMES), "-fps_mode", "passthrough", "-pix_fmt", "bgr24",
         "-f", "rawvideo", "pipe:1"],
        capture_output=True, timeout=90)
    assert done.returncode == 0, done.stderr.decode(errors="replace")
    frame_bytes = WIDTH * HEIGHT * 3
    raw = done.stdout
    pictures = [np.frombuffer(raw[i:i + frame_bytes], np.uint8).reshape(HEIGHT, WIDTH, 3)
                for i in range(0, len(raw) - frame_bytes + 1, frame_bytes)]
    return pictures, packets(crc.read_text()), first.read_bytes(), done.stderr.decode(errors="replace")


def test_twenty_fresh_rtsp_clients_get_whole_pictures_from_a_key_frame_with_increasing_time_stamps(
        service, tmp_path):
    http_url, rtsp_url = service
    for client in range(CLIENTS):
        pictures, sent, first, said = one_client(rtsp_url, tmp_path)
        where = f"client {client + 1} of {CLIENTS}"
        complaints = [line for line in said.splitlines() if COMPLAINTS.search(line)]
        assert not complaints, f"{where}: ffmpeg: {complaints[:5]}"
        assert len(pictures) == FRAMES and len(sent) >= FRAMES, f"{where}: {len(pictures)} pictures"
        assert sent[0][1], f"{where}: the first packet is not a key frame"
        types = nal_types(first)
        assert 5 in types and 7 in types[:types.index(5)] and 8 in types[:types.index(5)], \
            f"{where}: the first picture's NAL units {types}: no SPS and PPS before its IDR slice"
        # the first packet has no time stamp of its own at ffmpeg's RTSP demuxer, whatever the server
        dts = [d for d, _ in sent[1:]]
        assert all(b > a for a, b in zip(dts, dts[1:])), f"{where}: time stamps not increasing: {dts}"
        snapshot = cv2.imdecode(np.frombuffer(httpx.get(http_url + "/snapshot.jpg", timeout=10).content, np.uint8),
                                cv2.IMREAD_GRAYSCALE)
        assert snapshot.shape == (HEIGHT, WIDTH)
        for index, picture in enumerate(pictures):
            grey = cv2.cvtColor(picture, cv2.COLOR_BGR2GRAY)
            # the still scene: every picture is the snapshot's up to noise and coding; a smear or a
            # missing slice is tens of grey levels off over whole rows
            rows = np.abs(grey.astype(np.float32) - snapshot).mean(axis=1)
            assert rows.max() < 12, f"{where}, picture {index}: rows {int(rows.argmax())} off by {rows.max():.1f}"


def test_time_stamps_are_on_the_frame_grid_and_strictly_increase():
    from service.publishers.rtsp import next_pts

    interval = 33_333_333
    assert next_pts(0, None, interval) == 0
    assert next_pts(5_000_000, 0, interval) is None  # the frame pushed as the media starts: same slot as the first
    assert next_pts(40_000_000, 0, interval) == interval  # rounded down, never ahead of the running time
    assert next_pts(70_000_000, interval, interval) == 2 * interval
    # jitter: a frame in a taken slot takes the next one when that is at most half an interval ahead of it
    assert next_pts(60_000_000, interval, interval) == 2 * interval
    assert next_pts(40_000_000, interval, interval) is None  # 27 ms ahead: too close to the frame before
    stamps, last = [], None  # 30 fps with 2 ms of jitter across a slot's edge: every frame gets a stamp
    for k in range(1, 60):
        running = k * interval + (1_000_000 if k % 2 else -1_000_000)
        last = next_pts(running, last, interval) or last
        stamps.append(last)
    assert len(set(stamps)) == len(stamps) and all(b > a for a, b in zip(stamps, stamps[1:]))


def joiner(rtsp_url: str, folder: Path) -> subprocess.Popen:
    """An ffmpeg client joining the stream: 10 packets as received (framecrc), the first one's bytes, 10 decoded
    pictures; the probing is short (the SDP carries the stream's parameters)."""
    folder.mkdir()
    return subprocess.Popen(
        ["ffmpeg", "-nostdin", "-hide_banner", "-loglevel", "warning", "-probesize", "32", "-analyzeduration", "0",
         "-rtsp_transport", "tcp", "-i", rtsp_url,
         "-map", "0:v", "-frames:v", "10", "-c", "copy", "-copyinkf", "-f", "framecrc", "-y", str(folder / "crc"),
         "-map", "0:v", "-frames:v", "1", "-c", "copy", "-copyinkf", "-f", "h264", "-y", str(folder / "first"),
         "-map", "0:v", "-frames:v", "10", "-f", "null", "-"],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def test_late_joiners_of_a_playing_stream_start_at_a_key_frame_and_a_storm_forces_few(service, tmp_path):
    """20 clients join a stream another client plays (mid-GOP), in two bursts of 10 at once: each one's first
    packet is a key frame with SPS and PPS (before: 1 join in 10 got the GOP's next delta frame first), no
    decoder complaint for them or the client already playing, and the forced key frames are at least
    ``keyframe_gap_s`` (0.5 s) apart: a burst does not make every frame a key frame."""
    http_url, rtsp_url = service

    def rtsp_state() -> dict:
        return httpx.get(http_url + "/api/state", timeout=5).json()["rtsp"]

    holder = subprocess.Popen(["ffmpeg", "-nostdin", "-hide_banner", "-loglevel", "warning", "-rtsp_transport", "tcp",
                               "-i", rtsp_url, "-t", "60", "-f", "null", "-"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 20
        while rtsp_state()["clients"] < 1:
            assert holder.poll() is None and time.monotonic() < deadline, "the first client did not start playing"
            time.sleep(0.1)
        time.sleep(0.6)  # mid-GOP: the media's first key frame is behind
        before, started = rtsp_state(), time.monotonic()
        for burst in range(2):
            clients = [joiner(rtsp_url, tmp_path / f"{burst}-{k}") for k in range(10)]
            for k, client in enumerate(clients):
                where = f"joiner {burst * 10 + k + 1} of 20"
                _, said = client.communicate(timeout=60)
                assert client.returncode == 0, f"{where}: {said}"
                sent = packets((tmp_path / f"{burst}-{k}" / "crc").read_text())
                assert len(sent) == 10 and sent[0][1], f"{where}: the first packet is not a key frame: {sent[:3]}"
                complaints = [line for line in said.splitlines() if COMPLAINTS.search(line)]
                assert not complaints, f"{where}: ffmpeg: {complaints[:5]}; packets {sent}"
                types = nal_types((tmp_path / f"{burst}-{k}" / "first").read_bytes())
                assert 5 in types and {7, 8} <= set(types[:types.index(5)]), \
                    f"{where}: the first picture's NAL units {types}: no SPS and PPS before its IDR slice"
        elapsed, after = time.monotonic() - started, rtsp_state()
        forced = after["keyframes_forced"] - before["keyframes_forced"]
        assert after["joins_at_keyframe"] - before["joins_at_keyframe"] == 20
        assert forced <= elapsed / 0.5 + 1, f"{forced} key frames forced in {elapsed:.1f} s for 20 joins"
        assert after["waiting_for_keyframe"] == 0 and holder.poll() is None
    finally:
        holder.terminate()
        _, said = holder.communicate(timeout=10)
    complaints = [line for line in said.splitlines() if COMPLAINTS.search(line)]
    assert not complaints, f"the client playing throughout: ffmpeg: {complaints[:5]}"
