"""Decoding of every pixel format from raw bytes, against independent per-pixel reference encoders."""

from __future__ import annotations

import zlib

import numpy as np
import pytest

from svelive.capture.v4l2 import frame_from_buffer
from svelive.core import formats
from svelive.core.errors import SveliveError


def _bits_lsb(values: list[int], bits: int) -> bytes:
    """LSB-first bit stream (PFNC 'p' formats)."""
    acc = n = 0
    out = bytearray()
    for v in values:
        acc |= v << n
        n += bits
        while n >= 8:
            out.append(acc & 0xFF)
            acc >>= 8
            n -= 8
    if n:
        out.append(acc & 0xFF)
    return bytes(out)


def _bits_msb(values: list[int], bits: int) -> bytes:
    """MSB-first bit stream (V4L2 Y10B)."""
    s = "".join(format(v, f"0{bits}b") for v in values)
    s += "0" * (-len(s) % 8)
    return bytes(int(s[i:i + 8], 2) for i in range(0, len(s), 8))


def encode(values: list[int], packing: str, bits: int) -> bytes:
    out = bytearray()
    if packing == "gev_packed12":
        for a, b in zip(values[0::2], values[1::2]):
            out += bytes([a >> 4, (a & 0xF) | ((b & 0xF) << 4), b >> 4])
    elif packing == "gev_packed10":
        for a, b in zip(values[0::2], values[1::2]):
            out += bytes([a >> 2, (a & 0x3) | ((b & 0x3) << 4), b >> 2])
    elif packing in ("lsb12", "lsb10"):
        out += _bits_lsb(values, bits)
    elif packing == "msb10":
        out += _bits_msb(values, bits)
    elif packing == "mipi12":
        for a, b in zip(values[0::2], values[1::2]):
            out += bytes([a >> 4, b >> 4, (a & 0xF) | ((b & 0xF) << 4)])
    elif packing == "mipi10":
        for g in range(0, len(values), 4):
            p = values[g:g + 4]
            out += bytes([v >> 2 for v in p]) + bytes([sum((v & 3) << (2 * i) for i, v in enumerate(p))])
    elif packing == "none":
        for v in values:
            out += bytes([v]) if bits <= 8 else bytes([v & 0xFF, v >> 8])
    else:
        raise AssertionError(packing)
    return bytes(out)


@pytest.mark.parametrize("name", formats.names())
def test_every_format_decodes_reference_bytes(name: str) -> None:
    fmt = formats.lookup(name)
    h, w = 3, 8
    rng = np.random.default_rng(zlib.crc32(name.encode()))
    img = rng.integers(0, 2**fmt.bits, size=(h, w))
    img[0, :4] = [0, 2**fmt.bits - 1, 1, 2 ** (fmt.bits - 1)]  # extremes and single bits
    data = encode(img.reshape(-1).tolist(), fmt.packing, fmt.bits)
    out = formats.unpack(data, w, h, name)
    assert out.dtype == fmt.dtype and out.shape == (h, w)
    np.testing.assert_array_equal(out, img)


@pytest.mark.parametrize("name", ["Mono8", "Mono12", "Mono12Packed", "Mono10p", "Y10P", "BayerRG16"])
def test_row_stride_padding_is_skipped(name: str) -> None:
    fmt = formats.lookup(name)
    h, w = 4, 8
    img = np.arange(h * w).reshape(h, w) % (2**fmt.bits)
    stride = fmt.row_bytes(w) + 6
    rows = [encode(r.tolist(), fmt.packing, fmt.bits) + b"\xAA" * 6 for r in img]
    np.testing.assert_array_equal(formats.unpack(b"".join(rows), w, h, name, stride), img)
    # the last row's padding may be missing
    np.testing.assert_array_equal(formats.unpack(b"".join(rows)[:-6], w, h, name, stride), img)


def test_v4l2_fourcc_aliases_and_opencv_buffer() -> None:
    assert formats.lookup("Y12").name == "Mono12" and formats.lookup("grey").name == "Mono8"
    assert formats.lookup("BA81").name == "BayerBG8" and formats.lookup("RG16").name == "BayerRG16"
    assert formats.fourcc_text(0x59455247) == "GREY"
    img = (np.arange(6 * 10).reshape(6, 10) * 61) % 4096
    padded = np.zeros((6, 24), np.uint8)  # 20 bytes of pixels + 4 of driver padding per row
    padded[:, :20] = np.frombuffer(img.astype("<u2").tobytes(), np.uint8).reshape(6, 20)
    np.testing.assert_array_equal(frame_from_buffer(padded.reshape(1, -1), 10, 6, formats.lookup("Y12")), img)


def test_bad_input_is_a_clear_error() -> None:
    with pytest.raises(SveliveError, match="unknown pixel format 'RGB8'"):
        formats.lookup("RGB8")
    with pytest.raises(SveliveError, match="needs 48 bytes, got 47"):
        formats.unpack(b"\0" * 47, 8, 4, "Mono12Packed")
    with pytest.raises(SveliveError, match="stride 3 is less"):
        formats.unpack(b"\0" * 64, 8, 4, "Mono8", stride=3)
    with pytest.raises(SveliveError, match="whole number"):
        formats.unpack(b"\0" * 64, 7, 4, "Mono10p", stride=10)
