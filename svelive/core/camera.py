"""The camera description: everything reconstruction needs to know about the frames of one camera.

A :class:`Camera` is immutable. A source builds it once, from its pixel format
and the user's settings, and attaches it to every :class:`svelive.core.frame.Frame`;
a recording stores it; calibration produces a new one. Reconstruction reads it
from the frame, so the pattern is parsed once and the response curve and the
per-pixel exposure map are applied once, in :mod:`svelive.reconstruction.input`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from svelive.core.cfa import ColourFilter, joint_period
from svelive.core.errors import SveliveError
from svelive.core.pattern import Pattern, check_depth, minimal_tile
from svelive.core.response import Response
from svelive.core.sensor import Sensor, container_bits

#: Colour SVE layouts of real sensors: (exposure pattern, colour filter). Relative exposures are
#: examples (8 = 3 stops, the usual dual-ISO/dual-gain step); give another pattern of the same shape
#: for another ratio.
COLOUR_LAYOUTS: dict[str, tuple[str, str]] = {
    # Canon dual-ISO (Magic Lantern): pairs of rows at two gains, so each Bayer row phase has both
    "dual-iso": ("1/1/8/8", "RGGB"),
    # quad-Bayer (IMX294 class): the two diagonals of every same-colour 2x2 block at two gains
    "quad-bayer": ("1,8/8,1", "quad-RGGB"),
    # exposure alternating by column pairs on a Bayer mosaic
    "column-bayer": ("1,1,8,8", "RGGB"),
    # Narasimhan and Nayar's assorted pixels: one exposure per 2x2 Bayer cell, four over a 4x4 tile
    "assorted-4x4": ("1,1,4,4/1,1,4,4/16,16,64,64/16,16,64,64", "RGGB"),
}


@dataclass(frozen=True)
class Camera:
    """What one camera's raw frames are.

    Attributes:
        pattern: the exposure pattern (may carry a calibrated per-pixel map), or None
            when unknown (a recording made without one); reconstruction then refuses.
        cfa: the colour filter layout, in the phase of the delivered frame's top-left
            pixel, or None for a monochrome sensor.
        sensor: bit depth, black and white level, gain and read noise.
        response: the calibrated inverse response, or None for a linear sensor.
    """

    pattern: Pattern | None = None
    cfa: ColourFilter | None = None
    sensor: Sensor = Sensor()
    response: Response | None = None

    def __post_init__(self) -> None:
        if self.pattern is not None:
            check_depth(self.pattern, self.sensor.bits)

    @classmethod
    def build(cls, pattern: Pattern | str | None = None, cfa: ColourFilter | str | None = None,
              sensor: Sensor | None = None, response: Response | None = None) -> Camera:
        """A Camera from text forms or objects; a :data:`COLOUR_LAYOUTS` name as ``pattern`` sets both layers."""
        if isinstance(pattern, str) and pattern.strip() in COLOUR_LAYOUTS:
            exposures, layout_cfa = COLOUR_LAYOUTS[pattern.strip()]
            if cfa is not None and ColourFilter.parse(cfa) != ColourFilter.parse(layout_cfa):
                raise SveliveError(f"layout {pattern.strip()!r} has the colour filter {layout_cfa}, "
                                   f"but {cfa} was given: drop --cfa or give the exposure pattern itself")
            pattern, cfa = exposures, layout_cfa
        return cls(None if pattern is None else Pattern.parse(pattern),
                   None if cfa is None else ColourFilter.parse(cfa),
                   sensor if sensor is not None else Sensor(), response)

    @property
    def colour(self) -> bool:
        """True when the frames are colour mosaics."""
        return self.cfa is not None

    @property
    def channels(self) -> int:
        """Channels of a reconstructed frame: 3 with a CFA, else 1."""
        return 3 if self.cfa is not None else 1

    @property
    def period(self) -> tuple[int, int]:
        """The joint tile of exposure and colour (rows, cols)."""
        shapes = [layer.shape for layer in (self.pattern, self.cfa) if layer is not None]
        return joint_period(*shapes) if shapes else (1, 1)

    def replace(self, **changes: Any) -> Camera:
        """A copy with some fields changed (``dataclasses.replace``)."""
        return replace(self, **changes)

    def with_pattern(self, pattern: Pattern | str | None) -> Camera:
        return replace(self, pattern=None if pattern is None else Pattern.parse(pattern))

    def require_pattern(self) -> Pattern:
        """The exposure pattern; a one-line error naming the fix when it is unknown."""
        if self.pattern is None:
            raise SveliveError("the exposure pattern of these frames is unknown: give it (--pattern, e.g. 1,4/16,64)")
        return self.pattern

    def check(self, raw: np.ndarray) -> np.ndarray:
        """``raw`` as an array after checking it is a frame of this camera (one line on what is wrong)."""
        raw = np.asarray(raw)
        if raw.ndim == 3 and raw.shape[2] in (3, 4):
            raise SveliveError(f"raw frame has shape {raw.shape}: a demosaiced colour image, not a single-channel raw mosaic "
                               "(give the sensor's raw frame, one value per pixel)")
        if raw.ndim != 2:
            raise SveliveError(f"raw frame must be a single-channel 2-D array, got shape {raw.shape}")
        if raw.size == 0:
            raise SveliveError("raw frame is empty")
        if raw.dtype.kind not in "uif":
            raise SveliveError(f"raw frame has unsupported dtype {raw.dtype}")
        if raw.dtype.kind in "ui" and self.sensor.white_level > np.iinfo(raw.dtype).max:
            raise SveliveError(f"white level {self.sensor.white_level:g} exceeds the {raw.dtype} range")
        if raw.dtype.kind == "f" and not np.all(np.isfinite(raw)):
            raise SveliveError("raw frame contains NaN or inf")
        return raw

    # ----- stored form (recordings, EXR attributes) ---------------------------------
    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description. A per-pixel exposure map is not included (``pixel_map``: true says there was one)."""
        s = self.sensor
        return {"pattern": None if self.pattern is None else str(self.pattern),
                "pixel_map": self.pattern is not None and self.pattern.pixel_map is not None,
                "cfa": None if self.cfa is None else str(self.cfa),
                "sensor": {"bits": s.bits, "black_level": s.black_level, "white_level": s.white_level,
                           "gain": s.gain, "read_noise": s.read_noise},
                "response": None if self.response is None else self.response.to_dict()}

    @classmethod
    def from_dict(cls, data: dict[str, Any], *, default_bits: int = 16) -> Camera:
        """The inverse of :meth:`to_dict`; a one-line SveliveError for a malformed description."""
        if not isinstance(data, dict):
            raise SveliveError(f"camera description must be a JSON object, got {type(data).__name__}")
        s = data.get("sensor")
        s = {} if s is None else s
        if not isinstance(s, dict):
            raise SveliveError(f"camera sensor must be a JSON object, got {type(s).__name__}")
        for key in ("bits", "black_level", "white_level", "gain", "read_noise"):
            value = s.get(key)
            if value is not None and (isinstance(value, bool) or not isinstance(value, (int, float))):
                raise SveliveError(f"camera sensor is invalid ({key} must be a number, got {type(value).__name__} "
                                   f"{value!r:.40})")
            if isinstance(value, float) and not math.isfinite(value):
                raise SveliveError(f"camera sensor is invalid ({key} must be finite, got {value!r})")
        bits = default_bits if s.get("bits") is None else s["bits"]
        if not (1 <= bits <= 16 and float(bits).is_integer()):
            raise SveliveError(f"camera sensor is invalid (bits must be a whole number 1..16, got {bits!r:.20})")
        for key in ("pattern", "cfa"):
            if data.get(key) is not None and not isinstance(data[key], str):
                raise SveliveError(f"camera {key} must be text or null, got {type(data[key]).__name__}")
        response = data.get("response")
        if response is not None and not isinstance(response, dict):
            raise SveliveError(f"camera response must be a JSON object or null, got {type(response).__name__}")
        try:
            sensor = Sensor(int(bits), float(s.get("black_level") or 0.0), s.get("white_level"), s.get("gain"),
                            s.get("read_noise"))
        except (TypeError, ValueError, OverflowError) as exc:
            raise SveliveError(f"camera sensor is invalid ({exc})") from None
        return cls.build(data.get("pattern"), data.get("cfa"), sensor,
                         None if response is None else Response.from_dict(response))


def colour_phase(pattern: Pattern, cfa: ColourFilter, shape: tuple[int, int],
                 phase: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, Pattern]:
    """The pixels of one phase ``(qy, qx)`` of ``cfa.block_tile()`` in a frame of ``shape``: intp row
    and column indices (the frame's ``np.ix_(rows, cols)``, all behind one colour filter; whole
    same-colour blocks, so each keeps its block's exposures) and the exposure pattern they form
    (per-pixel exposure map cut alike)."""
    (by, bx), reduced = cfa.block_shape(), cfa.block_tile()
    period = joint_period(pattern.shape, cfa.shape)

    def keep(n: int, axis: int) -> np.ndarray:
        return np.flatnonzero(np.arange(n) // (by, bx)[axis] % reduced.shape[axis] == phase[axis])

    rows, cols = keep(shape[0], 0), keep(shape[1], 1)
    nominal = Pattern(pattern.tile).exposure_map(period)
    sub_tile = minimal_tile(nominal[np.ix_(keep(period[0], 0), keep(period[1], 1))])
    sub_map = None if pattern.pixel_map is None else np.ascontiguousarray(pattern.pixel_map[np.ix_(rows, cols)])
    return rows, cols, Pattern(sub_tile, sub_map)


def one_colour_plane(raw: np.ndarray, camera: Camera) -> tuple[np.ndarray, Pattern]:
    """The pixels of one colour of a colour SVE frame, as a monochrome SVE frame with its own pattern.

    For what must compare readings of one radiance only (the response fit): neighbouring pixels
    of different colour filters see different light. The colour is the CFA's most frequent one
    (green on a Bayer mosaic), its first phase (:func:`colour_phase`). ``raw`` (H, W) any dtype;
    returns (H', W') of it (a copy) and the sub-pattern. A monochrome camera's frame comes back
    as it is, with its pattern.
    """
    pattern = camera.require_pattern()
    cfa = camera.cfa
    if cfa is None:
        return raw, pattern
    reduced = cfa.block_tile()
    counts = np.bincount(reduced.ravel(), minlength=3)
    phase = tuple(int(v[0]) for v in np.nonzero(reduced == int(np.argmax(counts))))
    rows, cols, sub_pattern = colour_phase(pattern, cfa, raw.shape, phase)
    return np.ascontiguousarray(raw[np.ix_(rows, cols)]), sub_pattern


def camera_for_raw(raw: np.ndarray, pattern: Pattern | str | None, *, cfa: ColourFilter | str | None = None,
                   black_level: float = 0, white_level: float | None = None, gain: float | None = None,
                   read_noise: float | None = None, response: Response | None = None,
                   bits: int | None = None) -> Camera:
    """The Camera a bare raw array implies: bit depth ``bits``, else its dtype's, the rest as given (the library
    API's path)."""
    raw = np.asarray(raw)
    if bits is None:
        bits = container_bits(raw.dtype) if raw.dtype.kind in "ui" else 16
    if raw.dtype.kind in "ui" and white_level is not None and white_level > np.iinfo(raw.dtype).max:
        raise SveliveError(f"white level {white_level:g} exceeds the {raw.dtype} range")
    sensor = Sensor(bits=bits, black_level=float(black_level), white_level=white_level, gain=gain,
                    read_noise=read_noise)
    return Camera.build(pattern, cfa, sensor, response)
