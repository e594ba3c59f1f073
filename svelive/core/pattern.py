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

from svelive.core.errors import SveliveError

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

#: Largest exposure over smallest a pattern may have: 2^24, 24 stops (float32 carries 24 significant bits;
#: sensors' exposure ratios stay far below, dual gain ~2^3-2^5, optical SVE masks ~2^6-2^8).
MAX_RATIO = float(2**24)
#: Every exposure lies within [2^-24, 2^24]: with at most 16-bit readings, every value (raw - black) / e,
#: its square (variances) and its inverse (noise weights) stay inside float32's normal range with room to
#: spare. Further out float32 rounds an exposure to 0 or inf and reconstruction returns zeros.
EXPOSURE_RANGE = (float(2**-24), float(2**24))
#: Largest reconstructed value allowed, (2^bits - 1) / smallest exposure, in DN at exposure 1: 2^24, the
#: float32 integer range. The methods' noise weights are float32 with absolute floors; measured on flat
#: fields, `adaptive` goes wrong from about 2^27 (at 8, 12 and 16 bits alike), so this keeps 8x of margin.
MAX_VALUE = float(2**24)
#: unique_levels enumerates at most this many levels (distinct exposures x 2^bits).
MAX_ENUMERATED_LEVELS = 1 << 24


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
        check_exposures(tile)
        tile.setflags(write=False)
        object.__setattr__(self, "tile", tile)
        if self.pixel_map is not None:
            pmap = np.asarray(self.pixel_map, dtype=np.float32)
            if pmap.ndim != 2:
                raise SveliveError(f"per-pixel exposure map must be 2-D, got shape {pmap.shape}")
            if not np.all(np.isfinite(pmap)) or np.any(pmap <= 0):
                raise SveliveError("per-pixel exposure map must be finite and > 0 everywhere")
            check_exposures(pmap)
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
        try:
            return cls(np.array(rows, dtype=np.float64))
        except SveliveError as exc:
            raise SveliveError(f"pattern {spec!r}: {exc}") from None

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


def minimal_tile(tile: np.ndarray) -> np.ndarray:
    """The smallest tile that repeats to ``tile`` (per axis), e.g. the exposures of one colour-filter
    phase cut out of a joint tile; (th, tw) -> (th', tw'), same dtype."""
    for axis in (0, 1):
        n = tile.shape[axis]
        for size in range(1, n + 1):
            if n % size == 0 and np.array_equal(np.take(tile, np.arange(n) % size, axis=axis), tile):
                tile = np.take(tile, np.arange(size), axis=axis)
                break
    return tile


def check_exposures(exposures: np.ndarray) -> None:
    """Refuse relative exposures (finite, > 0) that float32 reconstruction cannot represent.

    One line naming the limit: each exposure within :data:`EXPOSURE_RANGE`, and the largest
    over the smallest at most :data:`MAX_RATIO`.
    """
    low, high = float(np.min(exposures)), float(np.max(exposures))
    lo, hi = EXPOSURE_RANGE
    if high / low > MAX_RATIO:
        raise SveliveError(f"exposures {low:g} to {high:g} span a ratio of {high / low:.3g}; at most 2^24 = "
                           f"{MAX_RATIO:.0f} (24 stops) can be reconstructed in float32")
    if low < lo or high > hi:
        value = low if low < lo else high
        raise SveliveError(f"exposure {value:g} is outside 2^-24..2^24 ({lo:.3g}..{hi:.3g}), where float32 "
                           "reconstruction holds its values: give relative exposures (e.g. 1,4/16,64)")


def check_depth(pattern: Pattern, bits: int) -> None:
    """Refuse (one line, naming the limit) a pattern whose smallest exposure would make a full-scale
    ``bits``-bit reading larger than :data:`MAX_VALUE` once divided by it."""
    low = float(pattern.levels[0]) if pattern.pixel_map is None else float(
        min(pattern.levels[0], float(pattern.pixel_map.min())))
    largest = (2**bits - 1) / low
    if largest > MAX_VALUE:
        raise SveliveError(f"pattern {pattern}: a full-scale {bits}-bit (--bits) reading at exposure {low:g} is {largest:.3g} "
                           f"DN at exposure 1, above the 2^24 = {MAX_VALUE:.0f} float32 reconstruction holds exactly; "
                           f"scale the exposures so the smallest is at least {(2**bits - 1) / MAX_VALUE:.3g} "
                           "(e.g. 1 for the shortest)")


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
    The union over exposures is enumerated with exact rational arithmetic, so
    coincident levels count once: the exposures relative to the smallest (the count
    does not depend on their scale) become fractions n/d (to 6 decimal places), each
    level q d / n is reduced by its gcd, and distinct (numerator, denominator) pairs
    are distinct levels. Every integer stays below 2^63 for ratios up to
    :data:`MAX_RATIO` and bits <= 16.
    """
    if not 1 <= bits <= 16:
        raise SveliveError(f"bit depth must be 1..16, got {bits}")
    levels = pattern.levels / pattern.levels[0]
    if levels.size * 2**bits > MAX_ENUMERATED_LEVELS:
        raise SveliveError(f"{levels.size} exposures x 2^{bits} levels is more than {MAX_ENUMERATED_LEVELS} to "
                           "enumerate: give a pattern with fewer distinct exposures")
    exposures = [Fraction(float(e)).limit_denominator(10**6) for e in levels]
    q = np.arange(2**bits, dtype=np.int64)
    num = np.concatenate([q * e.denominator for e in exposures])
    den = np.concatenate([np.full(q.size, e.numerator, np.int64) for e in exposures])
    g = np.gcd(num, den)  # gcd(0, n) = n: every zero level becomes 0/1
    return int(np.unique(np.stack([num // g, den // g], axis=1), axis=0).shape[0])
