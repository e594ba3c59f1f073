"""Exposure patterns: which relative exposure every pixel of the sensor has.

A pattern is a tile of relative exposures repeated over the frame from its
top-left pixel (text form ``"1,4/16,64"``: rows by ``/``, values by ``,``),
optionally refined by a full-frame per-pixel exposure map from a calibration
of a real, non-ideal mask. The theory of the paper's sections 4-5 (dynamic
range, unique quantisation levels) lives here too because it is a property of
the pattern and the bit depth alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from fractions import Fraction

import numpy as np

from svelive.errors import SveliveError

#: Named patterns. The paper's tile puts e3 e0 on the first row and e2 e1 on the
#: second, with e3 = 4 e2 = 16 e1 = 64 e0 (ratio 4) or ratio 2.
PRESETS: dict[str, str] = {
    "nayar-r4": "64,1/16,4",
    "nayar-r2": "8,1/4,2",
    "quad-r4": "1,4/16,64",
    "quad-r2": "1,2/4,8",
    "dual-rows-8": "1/1/8/8",
    "dual-rows-16": "1/16",
    "checker-16": "1,16/16,1",
}


@dataclass(frozen=True, eq=False)
class Pattern:
    """Relative exposures of the sensor's pixels.

    Attributes:
        tile: float64 array (th, tw), relative exposures, all > 0, repeated over
            the frame with its origin at the frame's top-left pixel.
        pixel_map: optional float32 array (H, W): the calibrated exposure of every
            pixel. When given it overrides the tile for frames of exactly that shape;
            the tile then states the nominal layout (which pixel is which level).
    """

    tile: np.ndarray
    pixel_map: np.ndarray | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        tile = np.asarray(self.tile, dtype=np.float64)
        if tile.ndim != 2 or tile.size == 0:
            raise SveliveError(f"exposure tile must be a non-empty 2-D array, got shape {tile.shape}")
        if not np.all(np.isfinite(tile)) or np.any(tile <= 0):
            raise SveliveError(f"exposures must be finite and > 0, got {tile.tolist()}")
        tile.setflags(write=False)
        object.__setattr__(self, "tile", tile)
        if self.pixel_map is not None:
            pmap = np.asarray(self.pixel_map, dtype=np.float32)
            if pmap.ndim != 2:
                raise SveliveError(f"per-pixel exposure map must be 2-D, got shape {pmap.shape}")
            if not np.all(np.isfinite(pmap)) or np.any(pmap <= 0):
                raise SveliveError("per-pixel exposure map must be finite and > 0 everywhere")
            pmap.setflags(write=False)
            object.__setattr__(self, "pixel_map", pmap)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Pattern):
            return NotImplemented
        return (np.array_equal(self.tile, other.tile) and self.pixel_map is other.pixel_map)

    def __hash__(self) -> int:
        return hash((self.tile.shape, self.tile.tobytes(), id(self.pixel_map)))

    # ----- construction -------------------------------------------------
    @classmethod
    def parse(cls, spec: str | Pattern) -> Pattern:
        """Pattern from its text form (``"1,4/16,64"``) or a preset name."""
        if isinstance(spec, Pattern):
            return spec
        if not isinstance(spec, str) or not spec.strip():
            raise SveliveError(f"pattern must be a non-empty string such as '1,4/16,64', got {spec!r}")
        text = PRESETS.get(spec.strip(), spec.strip())
        rows = []
        for r, row in enumerate(text.split("/")):
            values = []
            for item in row.split(","):
                try:
                    v = float(item.strip())
                    if not math.isfinite(v):
                        raise ValueError
                except ValueError:
                    raise SveliveError(
                        f"pattern {spec!r}: {item.strip()!r} in row {r + 1} is not a number "
                        f"(write rows separated by '/', values by ',', or a preset: {', '.join(PRESETS)})"
                    ) from None
                if not v > 0:
                    raise SveliveError(f"pattern {spec!r}: exposure {item.strip()!r} in row {r + 1} must be > 0")
                values.append(v)
            rows.append(values)
        widths = {len(r) for r in rows}
        if len(widths) != 1:
            raise SveliveError(f"pattern {spec!r}: rows have different lengths {[len(r) for r in rows]}")
        return cls(np.array(rows, dtype=np.float64))

    def with_pixel_map(self, pixel_map: np.ndarray) -> Pattern:
        """The same nominal tile with a calibrated per-pixel exposure map."""
        return Pattern(self.tile, pixel_map)

    # ----- properties ---------------------------------------------------
    @property
    def shape(self) -> tuple[int, int]:
        """Tile shape (rows, columns)."""
        return self.tile.shape  # type: ignore[return-value]

    @property
    def levels(self) -> np.ndarray:
        """The distinct nominal exposures, ascending, float64 (K,)."""
        return np.unique(self.tile)

    @property
    def ratio(self) -> float:
        """Largest over smallest exposure."""
        return float(self.tile.max() / self.tile.min())

    def __str__(self) -> str:
        return "/".join(",".join(f"{v:g}" for v in row) for row in self.tile)

    # ----- maps over a frame -------------------------------------------
    def exposure_map(self, shape: tuple[int, int]) -> np.ndarray:
        """Exposure of every pixel of a frame of ``shape``, float32 (H, W).

        Frames need not be a whole number of tiles: the tile is cut at the
        right and bottom edges.
        """
        h, w = shape
        if self.pixel_map is not None:
            if self.pixel_map.shape != (h, w):
                raise SveliveError(
                    f"per-pixel exposure map is {self.pixel_map.shape[1]}x{self.pixel_map.shape[0]} "
                    f"but the frame is {w}x{h}"
                )
            return self.pixel_map
        th, tw = self.shape
        reps = (-(-h // th), -(-w // tw))
        return np.ascontiguousarray(np.tile(self.tile.astype(np.float32), reps)[:h, :w])

    def level_index_map(self, shape: tuple[int, int]) -> np.ndarray:
        """Index into :attr:`levels` of every pixel's nominal exposure, uint8 (H, W)."""
        idx = np.searchsorted(self.levels, self.tile).astype(np.uint8)
        th, tw = self.shape
        h, w = shape
        return np.tile(idx, (-(-h // th), -(-w // tw)))[:h, :w]


# ----- theory (paper sections 4-5) ----------------------------------------

PAPER_DR_DB = 84.25  # 8 bits, e_max / e_min = 64
PAPER_Q = 869  # 8 bits (q = 256), K = 4, ratio 4


def dynamic_range_db(pattern: Pattern, bits: int) -> float:
    """SVE dynamic range, paper eq. 3: 20 log10((I_max / I_min) (e_max / e_min)), I_min = 1 DN."""
    i_max = 2**bits - 1
    return 20.0 * math.log10(i_max * pattern.ratio)


def dynamic_range_stops(pattern: Pattern, bits: int) -> float:
    """The same dynamic range in stops (log2)."""
    return math.log2((2**bits - 1) * pattern.ratio)


def unique_levels(pattern: Pattern, bits: int) -> int:
    """Number of distinct radiance values the pattern can report, counted exactly.

    Every exposure e_k quantises radiance to the levels q / e_k, q = 0 .. 2^bits - 1.
    The union over exposures is enumerated with exact rational arithmetic (the
    exposures are scaled to integers first), so coincident levels count once.
    """
    exposures = [Fraction(float(e)).limit_denominator(10**6) for e in pattern.levels]
    scale = math.lcm(*(e.numerator for e in exposures))
    q = np.arange(2**bits, dtype=np.int64)
    # q / (n/d) = q d / n, times the lcm of the numerators: an exact integer
    values = [q * (e.denominator * (scale // e.numerator)) for e in exposures]
    return int(np.unique(np.concatenate(values)).size)
