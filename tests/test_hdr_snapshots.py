"""HDR snapshots (issue 30 item 4): GET /snapshot.avif (PQ/HLG, 10/12 bit, BT.2020, CICP in the file) and
GET /snapshot.uhdr.jpg (Ultra HDR: SDR JPEG + gain map), against a real server, read back with real decoders
(libavif and libultrahdr via imagecodecs; ffprobe when installed); the colour functions against known values."""

from __future__ import annotations

import io
import json
import shutil
import struct
import subprocess
import sys

import httpx
import numpy as np
import pytest

from svelive import hdr_encode
from svelive.exr import read_exr

from tests.test_monitor import clipped_block_camera, pause
from tests.test_service_helpers import ServerThread

imagecodecs = pytest.importorskip("imagecodecs")


# ----- reading the files back ----------------------------------------------------------------------

def boxes(data: bytes, start: int = 0, end: int | None = None):
    """(type, payload start, payload end) of the ISOBMFF boxes in data[start:end], recursing into containers."""
    end = len(data) if end is None else end
    while start + 8 <= end:
        size, kind = struct.unpack(">I4s", data[start:start + 8])
        head = 8
        if size == 1:
            size, head = struct.unpack(">Q", data[start + 8:start + 16])[0], 16
        elif size == 0:
            size = end - start
        kind = kind.decode("latin1")
        yield kind, start + head, start + size
        if kind in ("meta", "iprp", "ipco"):
            yield from boxes(data, start + head + (4 if kind == "meta" else 0), start + size)
        start += size


def avif_properties(data: bytes) -> dict:
    """The AVIF's CICP (its colr nclx box) and bit depth (its av1C box)."""
    found = {}
    for kind, a, b in boxes(data):
        if kind == "colr" and data[a:a + 4] == b"nclx":
            primaries, transfer, matrix = struct.unpack(">HHH", data[a + 4:a + 10])
            found.update(primaries=primaries, transfer=transfer, matrix=matrix, full_range=bool(data[a + 10] >> 7))
        if kind == "av1C":
            flags = data[a + 2]
            high, twelve = bool(flags & 0x40), bool(flags & 0x20)
            found["bits"] = 12 if twelve else 10 if high else 8
    return found


def ffprobe(data: bytes) -> dict | None:
    if shutil.which("ffprobe") is None:
        return None
    out = subprocess.run(["ffprobe", "-v", "error", "-show_streams", "-of", "json", "-"], input=data,
                         capture_output=True, timeout=20, check=True).stdout
    return json.loads(out)["streams"][0]


def mid_grey(srv: ServerThread, frame_id: int) -> float:
    return httpx.get(srv.url + f"/api/pixel?x=0&y=0&frame={frame_id}", timeout=5).json()["mid_grey"]


# ----- the pure functions --------------------------------------------------------------------------

def test_pq_and_hlg_known_values():
    # SMPTE ST 2084: 100 cd/m2 -> 0.5081, 10 000 -> 1; BT.2408: 26 (grey card) -> 38 %, 203 (white) -> 58 %
    assert hdr_encode.pq_oetf(np.float32([0, 100, 10000, 20000])) == pytest.approx([0, 0.5081, 1, 1], abs=2e-4)
    assert hdr_encode.pq_oetf(hdr_encode.GREY_NITS) == pytest.approx(0.38, abs=1e-3)
    assert hdr_encode.pq_oetf(hdr_encode.REFERENCE_WHITE_NITS) == pytest.approx(0.58, abs=1e-3)
    # BT.2100 HLG: 1/12 -> 0.5, 1 -> 1, continuous; 75 % reference white is scene light 0.265
    assert hdr_encode.hlg_oetf(np.float32([0, 1 / 12, 1, 2])) == pytest.approx([0, 0.5, 1, 1], abs=1e-5)
    assert hdr_encode.hlg_light_of_signal(0.75) == pytest.approx(0.2650, abs=1e-3)
    for s in (0.2, 0.38, 0.5, 0.75, 0.95):
        assert hdr_encode.hlg_oetf(hdr_encode.hlg_light_of_signal(s)) == pytest.approx(s, abs=1e-5)
    assert hdr_encode.signal(np.float32(hdr_encode.GREY_NITS), "hlg") == pytest.approx(0.38, abs=1e-5)


def test_bt2020_conversion_keeps_white_and_puts_grey_at_26_nits():
    assert hdr_encode.REC709_TO_BT2020.sum(axis=1) == pytest.approx([1, 1, 1], abs=1e-9)
    image = np.float32([[[5.0, 5.0, 5.0], [5.0, 0.0, 0.0]]])
    nits = hdr_encode.bt2020_nits(image, np.eye(3), grey=5.0)
    assert nits[0, 0] == pytest.approx([26, 26, 26], rel=1e-5)
    assert nits[0, 1] == pytest.approx(26 * hdr_encode.REC709_TO_BT2020[:, 0], rel=1e-5)  # Rec.709 red in BT.2020
    wb = np.diag([2.0, 1.0, 0.5])  # the display matrix (white balance) is applied first
    assert hdr_encode.bt2020_nits(np.float32([[[2.5, 5, 10]]]), wb, 5.0)[0, 0] == pytest.approx([26] * 3, rel=1e-5)
    mono = hdr_encode.bt2020_nits(np.float32([[10.0, -1.0]]), None, grey=10.0)
    assert mono.shape == (1, 2, 3) and mono[0, 0] == pytest.approx([26] * 3) and (mono[0, 1] == 0).all()
    assert hdr_encode.quantise(np.float32([0, 0.5, 1, 2]), 10).tolist() == [0, 512, 1023, 1023]
    with pytest.raises(Exception, match="transfer must be one of pq, hlg"):
        hdr_encode.check_transfer("srgb")


# ----- a real server ---------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def mono():
    camera = clipped_block_camera()
    with ServerThread(camera) as srv:
        frame_id = pause(srv, camera)
        yield srv, frame_id, srv.pipeline.latest().hdr.image, mid_grey(srv, frame_id)


def near_grey(image: np.ndarray, grey: float) -> np.ndarray:
    lum = image if image.ndim == 2 else image.mean(axis=2)
    mask = np.abs(lum / grey - 1) < 0.05
    assert mask.sum() >= 20, "the scene should have pixels at mid-grey"
    return mask


@pytest.mark.parametrize("transfer, bits", [("pq", 10), ("hlg", 12)])
def test_avif_mono_cicp_bit_depth_and_mid_grey(mono, transfer, bits):
    srv, frame_id, image, grey = mono
    params = {"frame": frame_id} if transfer == "pq" else {"frame": frame_id, "transfer": transfer, "bits": bits}
    r = httpx.get(srv.url + "/snapshot.avif", params=params, timeout=30)
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "image/avif" and int(r.headers["x-frame-id"]) == frame_id
    props = avif_properties(r.content)
    code = hdr_encode.TRANSFERS[transfer]
    assert props == {"primaries": 9, "transfer": code, "matrix": 9, "full_range": True, "bits": bits}
    probe = ffprobe(r.content)
    if probe is not None:
        assert probe["color_primaries"] == "bt2020"
        assert probe["color_transfer"] == {"pq": "smpte2084", "hlg": "arib-std-b67"}[transfer]
        assert probe["pix_fmt"].endswith(f"{bits}le")
    decoded = imagecodecs.avif_decode(r.content)
    assert decoded.dtype == np.uint16 and decoded.shape == image.shape + (3,)
    top = (1 << bits) - 1
    assert decoded.max() <= top and decoded.max() > top // 2  # the clipped block is bright
    assert (np.abs(decoded[..., 0].astype(int) - decoded[..., 2]) <= top * 0.01).all()  # grey in every channel
    intended = round(0.38 * top)  # BT.2408's grey card: 26 cd/m2 in PQ, 38 % in HLG
    at_grey = decoded[..., 1][near_grey(image, grey)]
    assert abs(np.median(at_grey) - intended) <= 0.015 * top, (np.median(at_grey), intended)
    expected = hdr_encode.quantise(hdr_encode.signal(image / grey * hdr_encode.GREY_NITS, transfer), bits)
    assert np.median(np.abs(decoded[..., 1].astype(int) - expected)) <= 0.01 * top


def test_ultrahdr_jpeg_has_a_gain_map_and_decodes_to_hdr(mono):
    srv, frame_id, image, grey = mono
    r = httpx.get(srv.url + f"/snapshot.uhdr.jpg?frame={frame_id}", timeout=30)
    assert r.status_code == 200, r.text
    data = r.content
    assert r.headers["content-type"] == "image/jpeg" and data[:2] == b"\xff\xd8"
    # MPF in the primary image: two images, the second (the gain map) a JPEG where the index says
    mpf = data.find(b"MPF\x00")
    assert 0 < mpf < 200
    tiff = mpf + 4
    endian = "<" if data[tiff:tiff + 2] == b"II" else ">"
    entries = {}
    ifd = tiff + struct.unpack(endian + "I", data[tiff + 4:tiff + 8])[0]
    for i in range(struct.unpack(endian + "H", data[ifd:ifd + 2])[0]):
        tag, _, count, value = struct.unpack(endian + "HHII", data[ifd + 2 + 12 * i:ifd + 14 + 12 * i])
        entries[tag] = (count, value)
    assert struct.unpack(endian + "I", data[tiff + 4:tiff + 8]) and entries[0xB001][1] == 2  # NumberOfImages
    index = tiff + entries[0xB002][1]
    _, size, offset, _ = struct.unpack(endian + "IIIH", data[index + 16:index + 30])
    second = tiff + offset
    assert data[second:second + 2] == b"\xff\xd8" and second + size == len(data)
    # ISO 21496-1 gain-map metadata: the version in the primary, the parameters in the gain map
    iso = b"urn:iso:std:iso:ts:21496:-1\x00"
    assert data.find(iso) < 64 and data.find(iso, second) > second
    assert imagecodecs.ultrahdr_check(data)
    # every other viewer: an 8-bit SDR JPEG of the frame
    from PIL import Image
    sdr = Image.open(io.BytesIO(data))
    assert sdr.size == image.shape[::-1] and sdr.mode == "RGB"
    # an HDR display: linear light with reference white at 1, mid-grey at 26/203, the clipped block far above 1
    hdr = imagecodecs.ultrahdr_decode(data, transfer=imagecodecs.ULTRAHDR.CT.LINEAR).astype(np.float32)
    at_grey = hdr[..., 1][near_grey(image, grey)]
    assert np.median(at_grey) == pytest.approx(26 / 203, rel=0.15)
    assert np.median(hdr[40:80, 60:120, 1]) > 3.0


def test_avif_colour_is_the_exr_snapshot_in_bt2020():
    from tests.test_service_colour import ColourServer, make_colour_camera

    camera = make_colour_camera(fps=10.0)
    colour = {"colour_matrix": [1.5, -0.3, -0.2, -0.2, 1.4, -0.2, 0.0, -0.4, 1.4], "output_space": "rec709"}
    with ColourServer(camera) as srv:
        srv.pipeline.update_settings(colour=colour)  # the EXR and the AVIF both in (converted) Rec.709
        frame_id = pause(srv, camera)
        exr = httpx.get(srv.url + "/snapshot.exr", timeout=10)
        assert int(exr.headers["x-frame-id"]) == frame_id
        channels, attributes = read_exr(exr.content)
        assert attributes["colourSpace"] == "rec709"
        grey = mid_grey(srv, frame_id)
        r = httpx.get(srv.url + f"/snapshot.avif?frame={frame_id}", timeout=30)
        assert r.status_code == 200, r.text
    assert avif_properties(r.content) == {"primaries": 9, "transfer": 16, "matrix": 9, "full_range": True,
                                          "bits": 10}
    rec709 = np.stack([channels[c] for c in "RGB"], axis=-1).astype(np.float64)
    nits = np.maximum(rec709 @ hdr_encode.REC709_TO_BT2020.T, 0) / grey * 26.0
    expected = np.rint(np.clip(hdr_encode.pq_oetf(nits), 0, 1) * 1023)
    decoded = imagecodecs.avif_decode(r.content).astype(np.float64)
    assert decoded.shape == expected.shape
    for c in range(3):
        assert np.median(np.abs(decoded[..., c] - expected[..., c])) <= 6, c
    assert np.abs(decoded[..., 0] - decoded[..., 2]).mean() > 5  # colour, not grey


def test_missing_extra_is_one_line_503(mono, monkeypatch):
    srv, frame_id, _, _ = mono
    monkeypatch.setitem(sys.modules, "imagecodecs", None)  # import imagecodecs now raises ImportError
    for path in ("/snapshot.avif", "/snapshot.uhdr.jpg"):
        r = httpx.get(srv.url + path, timeout=10)
        assert r.status_code == 503
        detail = r.json()["detail"]
        assert "\n" not in detail and 'pip install "svelive[hdr]"' in detail
    r = httpx.get(srv.url + "/snapshot.avif?transfer=srgb", timeout=10)
    assert r.status_code == 422 and "pq, hlg" in r.json()["detail"]
