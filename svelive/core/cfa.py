"""Colour filter arrays (CFA): which colour every pixel of the sensor sees.

A CFA is a tile of colour letters repeated over the frame from its top-left
pixel, written in the same text form as exposure patterns: rows by ``/``,
letters by ``,`` (``"R,G/G,B"``), or a preset name (``RGGB``, ``GRBG``,
``GBRG``, ``BGGR``, ``quad-RGGB``). The exposure pattern and the CFA may have
different periods; a frame's joint period is their least common multiple
(:func:`joint_period`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from svelive.core.errors import SveliveError

#: Channel index of each colour letter; the output's channel axis is in this order.
CHANNELS = "RGB"

#: Named layouts. quad-RGGB is the quad-Bayer (Sony IMX294-class) layout: 2x2 blocks of one colour.
PRESETS: dict[str, str] = {
    "RGGB": "R,G/G,B",
    "GRBG": "G,R/B,G",
    "GBRG": "G,B/R,G",
    "BGGR": "B,G/G,R",
    "quad-RGGB": "R,R,G,G/R,R,G,G/G,G,B,B/G,G,B,B",
}


@dataclass(frozen=True, eq=False)
class ColourFilter:
    """A colour filter layout.

    Attributes:
        tile: uint8 array (th, tw) of channel indices (0 = R, 1 = G, 2 = B),
            repeated over the frame with its origin at the top-left pixel;
            every channel appears at least once.
    """

    tile: np.ndarray

    def __post_init__(self) -> None:
        tile = np.asarray(self.tile)
        if tile.ndim != 2 or tile.size == 0:
            raise SveliveError(f"colour filter tile must be a non-empty 2-D array, got shape {tile.shape}")
        if np.any(tile < 0) or np.any(tile > 2):
            raise SveliveError("colour filter tile holds a channel index other than 0 (R), 1 (G), 2 (B)")
        tile = tile.astype(np.uint8)
        missing = [CHANNELS[c] for c in range(3) if not np.any(tile == c)]
        if missing:
            raise SveliveError(f"colour filter {self._text(tile)}: R, G and B must each appear "
                               f"(missing: {', '.join(missing)})")
        tile.setflags(write=False)
        object.__setattr__(self, "tile", tile)

    def block_shape(self) -> tuple[int, int]:
        """The largest (rows, cols) blocks of one colour the tile is made of ((2, 2) for quad-RGGB)."""
        tile = self.tile

        def along(axis: int) -> int:
            n = tile.shape[axis]
            for size in range(n, 0, -1):
                if n % size == 0:
                    starts = np.take(tile, np.arange(n) // size * size, axis=axis)
                    if np.array_equal(starts, tile):
                        return size
            return 1

        return along(0), along(1)

    def block_tile(self) -> np.ndarray:
        """The tile with each block of one colour (:meth:`block_shape`) as one entry: uint8, (2, 2)
        RGGB for both RGGB and quad-RGGB."""
        by, bx = self.block_shape()
        return self.tile[::by, ::bx]

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, ColourFilter):
            return NotImplemented
        return np.array_equal(self.tile, other.tile)

    def __hash__(self) -> int:
        return hash((self.tile.shape, self.tile.tobytes()))

    @classmethod
    def parse(cls, spec: str | ColourFilter) -> ColourFilter:
        """A CFA from its text form (``"R,G/G,B"``), a preset name, or a compact 2x2 name like ``"rggb"``."""
        if isinstance(spec, ColourFilter):
            return spec
        if not isinstance(spec, str) or not spec.strip():
            raise SveliveError(f"colour filter must be text such as 'RGGB' or 'R,G/G,B', got {spec!r}")
        name = spec.strip()
        presets = {k.lower(): v for k, v in PRESETS.items()}
        text = presets.get(name.lower(), name)
        rows = []
        for r, row in enumerate(text.split("/")):
            letters = [item.strip().upper() for item in row.split(",")]
            bad = [x for x in letters if x not in ("R", "G", "B")]
            if bad:
                raise SveliveError(f"colour filter {spec!r}: {bad[0]!r} in row {r + 1} is not R, G or B "
                                   f"(write rows separated by '/', letters by ',', or a preset: {', '.join(PRESETS)})")
            rows.append([CHANNELS.index(x) for x in letters])
        if len({len(r) for r in rows}) != 1:
            raise SveliveError(f"colour filter {spec!r}: rows have different lengths {[len(r) for r in rows]}")
        return cls(np.array(rows, np.uint8))

    @property
    def shape(self) -> tuple[int, int]:
        """Tile shape (rows, columns)."""
        return self.tile.shape  # type: ignore[return-value]

    @property
    def name(self) -> str:
        """The preset name when the tile is one, else the text form."""
        text = str(self)
        return next((k for k, v in PRESETS.items() if v == text), text)

    def __str__(self) -> str:
        return self._text(self.tile)

    @staticmethod
    def _text(tile: np.ndarray) -> str:
        return "/".join(",".join(CHANNELS[c] for c in row) for row in np.asarray(tile))

    def shifted(self, rows: int, cols: int) -> ColourFilter:
        """The layout seen by a region whose top-left pixel is at (rows, cols) of this one (e.g. a camera ROI offset)."""
        th, tw = self.shape
        return ColourFilter(np.roll(self.tile, (-(rows % th), -(cols % tw)), axis=(0, 1)))

    def channel_map(self, shape: tuple[int, int]) -> np.ndarray:
        """Channel index of every pixel of a frame of ``shape``, uint8 (H, W)."""
        th, tw = self.shape
        h, w = shape
        return np.ascontiguousarray(np.tile(self.tile, (-(-h // th), -(-w // tw)))[:h, :w])

    def is_bayer(self) -> bool:
        """True for a 2x2 tile with two greens on a diagonal (the four Bayer phases)."""
        return self.shape == (2, 2) and str(self) in (PRESETS[k] for k in ("RGGB", "GRBG", "GBRG", "BGGR"))


def joint_period(*shapes: tuple[int, int]) -> tuple[int, int]:
    """The least common multiple of tile shapes (rows, cols): the period of the joint layout."""
    return math.lcm(*(s[0] for s in shapes)), math.lcm(*(s[1] for s in shapes))
