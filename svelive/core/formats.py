"""Raw pixel formats: their names (GigE Vision PFNC and V4L2 fourcc) and unpacking.

Every format decodes to a 2-D numpy array, uint8 for 8-bit formats and uint16
for everything wider, holding the sensor value in its low bits (a Mono12 pixel
is 0..4095, never shifted up). Unpacking is vectorised over whole rows: a
packed format is viewed as groups of bytes (``(rows, groups, bytes_per_group)``)
and every output pixel of a group is one numpy expression.

Packings (``p`` = pixel, bits numbered from 0 = least significant):

========================  =======================================================
``none``                  one pixel per 1 or 2 bytes, 16-bit little-endian
``gev_packed12``          GigE Vision ``Mono12Packed``: 2 px in 3 bytes,
                          b0 = p0[11:4], b1 = p0[3:0] | p1[3:0] << 4, b2 = p1[11:4]
``gev_packed10``          GigE Vision ``Mono10Packed``: 2 px in 3 bytes,
                          b0 = p0[9:2], b1 = p0[1:0] | p1[1:0] << 4, b2 = p1[9:2]
``lsb12``                 PFNC ``Mono12p``: LSB-first bit stream, 2 px in 3 bytes
``lsb10``                 PFNC ``Mono10p``: LSB-first bit stream, 4 px in 5 bytes
``mipi12``                V4L2 ``Y12P`` (MIPI RAW12): b0 = p0[11:4], b1 = p1[11:4],
                          b2 = p0[3:0] | p1[3:0] << 4
``mipi10``                V4L2 ``Y10P`` (MIPI RAW10): b0..b3 = p0..p3[9:2],
                          b4 = p0[1:0] | p1[1:0] << 2 | p2[1:0] << 4 | p3[1:0] << 6
``msb10``                 V4L2 ``Y10B``: MSB-first bit stream, 4 px in 5 bytes
========================  =======================================================
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from svelive.core.cfa import ColourFilter
from svelive.core.errors import SveliveError


@dataclass(frozen=True)
class PixelFormat:
    """One wire format.

    Attributes:
        name: canonical name (GigE Vision PFNC spelling, e.g. ``"Mono12Packed"``).
        bits: significant bits per pixel of the decoded value.
        packing: one of the packings in the module docstring.
        cfa: colour filter layout of the top-left 2x2 cell ("RGGB", ...) or None for mono.
        aliases: other names accepted for it (V4L2 fourccs, display names).
    """

    name: str
    bits: int
    packing: str = "none"
    cfa: str | None = None
    aliases: tuple[str, ...] = ()

    @property
    def dtype(self) -> np.dtype:
        """numpy dtype of the decoded array: uint8 for 8-bit formats, else uint16."""
        return np.dtype(np.uint8) if self.bits <= 8 and self.packing == "none" else np.dtype(np.uint16)

    @property
    def group(self) -> tuple[int, int]:
        """(pixels, bytes) of one packing group."""
        return _GROUPS[self.packing] if self.packing != "none" else (1, 1 if self.bits <= 8 else 2)

    def row_bytes(self, width: int) -> int:
        """Bytes of ``width`` pixels without padding (a packed row must be whole groups)."""
        px, nb = self.group
        if width % px:
            raise SveliveError(f"{self.name}: a row of {width} pixels is not a whole number of {px}-pixel groups")
        return width // px * nb

    def frame_bytes(self, width: int, height: int) -> int:
        """Bytes of a tightly packed ``width`` x ``height`` frame."""
        px, nb = self.group
        n = width * height
        return -(-n // px) * nb


_GROUPS = {
    "gev_packed12": (2, 3), "gev_packed10": (2, 3), "lsb12": (2, 3), "mipi12": (2, 3),
    "lsb10": (4, 5), "mipi10": (4, 5), "msb10": (4, 5),
}

# V4L2 fourccs of the Bayer families, by layout: (8-bit, 10-bit, 12-bit, 16-bit)
_V4L2_BAYER = {
    "RGGB": ("RGGB", "RG10", "RG12", "RG16"),
    "GRBG": ("GRBG", "BA10", "BA12", "GR16"),
    "GBRG": ("GBRG", "GB10", "GB12", "GB16"),
    "BGGR": ("BA81", "BG10", "BG12", "BYR2"),
}
_GEV_BAYER = {"RGGB": "RG", "GRBG": "GR", "GBRG": "GB", "BGGR": "BG"}


def _table() -> dict[str, PixelFormat]:
    formats = [
        PixelFormat("Mono8", 8, aliases=("GREY", "Y8", "Y800")),
        PixelFormat("Mono10", 10, aliases=("Y10",)),
        PixelFormat("Mono12", 12, aliases=("Y12",)),
        PixelFormat("Mono14", 14, aliases=("Y14",)),
        PixelFormat("Mono16", 16, aliases=("Y16",)),
        PixelFormat("Mono10Packed", 10, "gev_packed10"),
        PixelFormat("Mono12Packed", 12, "gev_packed12"),
        PixelFormat("Mono10p", 10, "lsb10"),
        PixelFormat("Mono12p", 12, "lsb12"),
        PixelFormat("Y10P", 10, "mipi10", aliases=("Mono10MIPI",)),
        PixelFormat("Y12P", 12, "mipi12", aliases=("Mono12MIPI",)),
        PixelFormat("Y10B", 10, "msb10", aliases=("Y10BPACK",)),
    ]
    for cfa, short in _GEV_BAYER.items():
        f8, f10, f12, f16 = _V4L2_BAYER[cfa]
        formats += [
            PixelFormat(f"Bayer{short}8", 8, cfa=cfa, aliases=(f8,)),
            PixelFormat(f"Bayer{short}10", 10, cfa=cfa, aliases=(f10,)),
            PixelFormat(f"Bayer{short}12", 12, cfa=cfa, aliases=(f12,)),
            PixelFormat(f"Bayer{short}16", 16, cfa=cfa, aliases=(f16,)),
            PixelFormat(f"Bayer{short}12Packed", 12, "gev_packed12", cfa=cfa),
            PixelFormat(f"Bayer{short}10p", 10, "lsb10", cfa=cfa),
            PixelFormat(f"Bayer{short}12p", 12, "lsb12", cfa=cfa),
        ]
    table: dict[str, PixelFormat] = {}
    for f in formats:
        for key in (f.name, *f.aliases):
            table[key.lower()] = f
    return table


#: Every known format by lower-cased name or alias (read-only by convention).
FORMATS: dict[str, PixelFormat] = _table()


def names() -> list[str]:
    """Canonical names of all known formats."""
    return sorted({f.name for f in FORMATS.values()})


def lookup(name: str | PixelFormat) -> PixelFormat:
    """The format called ``name`` (PFNC name or V4L2 fourcc, case-insensitive)."""
    if isinstance(name, PixelFormat):
        return name
    fmt = find(name)
    if fmt is None:
        raise SveliveError(f"unknown pixel format {name!r}; known: {', '.join(names())}")
    return fmt


def find(name: str) -> PixelFormat | None:
    """The format called ``name``, or None when it is not one this module knows (a free-form label)."""
    return FORMATS.get(str(name).strip().lower())


def unpacked_name(bits: int, cfa: object = None) -> str:
    """The narrowest unpacked format holding ``bits``-bit values: ``Mono<n>``, or ``Bayer<XY><n>`` for a
    2x2 Bayer colour filter (a :class:`svelive.core.cfa.ColourFilter` or its name); any other filter, which
    has no PFNC name, gets the Mono name."""
    layout = None if cfa is None else ColourFilter.parse(cfa)  # type: ignore[arg-type]
    if layout is not None and layout.is_bayer():
        short, widths = _GEV_BAYER[layout.name], (8, 10, 12, 16)
        return next(f"Bayer{short}{b}" for b in widths if bits <= b)
    return next(f"Mono{b}" for b in (8, 10, 12, 14, 16) if bits <= b)


def fourcc_text(code: int) -> str:
    """A V4L2 fourcc integer (little-endian characters) as its 4-character text."""
    return "".join(chr((int(code) >> (8 * i)) & 0xFF) for i in range(4)).rstrip("\x00 ")


def _decode_groups(g: np.ndarray, packing: str) -> np.ndarray:
    """Decode packed groups uint8 (rows, n, bytes) into uint16 (rows, n * pixels)."""
    b = [g[..., i].astype(np.uint16) for i in range(g.shape[-1])]
    if packing == "gev_packed12":
        px = [(b[0] << 4) | (b[1] & 0xF), (b[2] << 4) | (b[1] >> 4)]
    elif packing == "gev_packed10":
        px = [(b[0] << 2) | (b[1] & 0x3), (b[2] << 2) | ((b[1] >> 4) & 0x3)]
    elif packing == "lsb12":
        px = [b[0] | ((b[1] & 0xF) << 8), (b[1] >> 4) | (b[2] << 4)]
    elif packing == "mipi12":
        px = [(b[0] << 4) | (b[2] & 0xF), (b[1] << 4) | (b[2] >> 4)]
    elif packing == "lsb10":
        px = [b[0] | ((b[1] & 0x3) << 8), (b[1] >> 2) | ((b[2] & 0xF) << 6),
              (b[2] >> 4) | ((b[3] & 0x3F) << 4), (b[3] >> 6) | (b[4] << 2)]
    elif packing == "mipi10":
        px = [(b[i] << 2) | ((b[4] >> (2 * i)) & 0x3) for i in range(4)]
    elif packing == "msb10":
        px = [(b[0] << 2) | (b[1] >> 6), ((b[1] & 0x3F) << 4) | (b[2] >> 4),
              ((b[2] & 0xF) << 6) | (b[3] >> 2), ((b[3] & 0x3) << 8) | b[4]]
    else:  # pragma: no cover - the table holds only the packings above
        raise SveliveError(f"unknown packing {packing!r}")
    out = np.empty(g.shape[:-1] + (len(px),), dtype=np.uint16)
    for i, p in enumerate(px):
        out[..., i] = p
    return out.reshape(g.shape[0], -1)


def unpack(data: bytes | bytearray | memoryview | np.ndarray, width: int, height: int,
           pixel_format: str | PixelFormat, stride: int | None = None, *, copy: bool = True) -> np.ndarray:
    """Decode one raw frame.

    Args:
        data: the frame's bytes (any buffer; a numpy array is viewed as bytes).
        width, height: frame size in pixels.
        pixel_format: format name or fourcc (see :func:`lookup`).
        stride: bytes from the start of one row to the next; None means rows are
            tightly packed (a packed format is then one bit stream over the frame,
            so rows need not hold whole groups).
        copy: for unpacked formats, False returns a view of ``data`` where possible.

    Returns:
        uint8 (8-bit unpacked formats) or uint16 array (height, width), in DN.
    """
    fmt = lookup(pixel_format)
    if width <= 0 or height <= 0:
        raise SveliveError(f"frame size must be positive, got {width}x{height}")
    buf = np.frombuffer(data, dtype=np.uint8) if not isinstance(data, np.ndarray) else data.reshape(-1).view(np.uint8)
    px, nb = fmt.group
    if stride is None:
        need = fmt.frame_bytes(width, height)
        if buf.size < need:
            raise SveliveError(f"{fmt.name} {width}x{height} needs {need} bytes, got {buf.size}")
        rows = buf[:need].reshape(1, need)
    else:
        row = fmt.row_bytes(width)
        if stride < row:
            raise SveliveError(f"{fmt.name}: row stride {stride} is less than the {row} bytes of a {width}-pixel row")
        need = stride * (height - 1) + row
        if buf.size < need:
            raise SveliveError(f"{fmt.name} {width}x{height} with stride {stride} needs {need} bytes, got {buf.size}")
        if buf.size < stride * height:  # the last row's padding may be absent
            buf = np.concatenate([buf[:need], np.zeros(stride * height - need, np.uint8)])
        rows = buf[: stride * height].reshape(height, stride)[:, :row]
    if fmt.packing == "none":
        if nb == 1:
            out = rows.reshape(-1)[: width * height] if stride is None else rows
        else:
            flat = np.ascontiguousarray(rows)
            out = flat.view("<u2")
            out = out.reshape(-1)[: width * height] if stride is None else out
            if out.dtype != np.uint16:
                out = out.astype(np.uint16)
        out = out.reshape(height, width)
        if copy or not out.flags.c_contiguous:
            out = np.array(out, copy=True)
        return out
    groups = rows.reshape(rows.shape[0], -1, nb)
    out = _decode_groups(groups, fmt.packing)
    return np.ascontiguousarray(out.reshape(-1)[: width * height].reshape(height, width))


def pack(image: np.ndarray, pixel_format: str | PixelFormat) -> bytes:
    """Encode ``image`` (H, W) into ``pixel_format``'s tightly packed bytes (for tests and fakes).

    Only unpacked formats and the 8/16-bit containers are supported; packed
    formats are produced by the independent reference encoders in the tests.
    """
    fmt = lookup(pixel_format)
    if fmt.packing != "none":
        raise SveliveError(f"packing into {fmt.name} is not supported")
    return np.ascontiguousarray(image, dtype=fmt.dtype.newbyteorder("<")).tobytes()
