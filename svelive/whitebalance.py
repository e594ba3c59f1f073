"""White balance and the camera-to-Rec.709 matrix: the one home of a colour frame's colour at the output.

A colour reconstruction is linear *camera* RGB: each channel in DN at relative
exposure 1, seen through the sensor's own filters, before any white balance
(svelive.reconstruct). Two steps turn it into something a display or a grader
understands:

- white balance: per-channel multipliers, green = 1, so that a neutral surface
  under the scene's light reads R = G = B. Fixed (the user's numbers) or
  automatic: a robust grey-world estimate over the well-exposed pixels of each
  frame (:func:`estimate_white_balance`), smoothed over frame time by
  :class:`WhiteBalancer` as svelive.tonemap.ToneMapper smooths exposure;
- an optional 3x3 matrix from white-balanced camera RGB to linear Rec.709
  (sRGB primaries, D65 white). Whether its rows sum to 1 (white preserved) is
  the user's business; it is only checked to be 3x3 and finite.

The composite camera -> output matrix is ``M @ diag(wb)`` (:func:`output_matrix`),
applied in one pass (:func:`apply_matrix`). ``output_space`` says what an EXR
holds: ``"camera"``, the reconstruction as it is (the white balance in use goes
into the attributes, not into the data), or ``"rec709"``, ``M @ diag(wb)`` applied.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from svelive.core.errors import SveliveError
from svelive.core.order import order_statistic
from svelive.exr import LUMA_WEIGHTS, REC709_CHROMATICITIES, image_channels
from svelive.tonemap import smoothing_factor

#: What an EXR of a colour frame holds (see the module docstring).
OUTPUT_SPACES = ("camera", "rec709")

#: White balance multipliers are kept within 2^-6..2^6 of green (a 6-stop cast is far beyond any light source).
MAX_MULTIPLIER = 64.0

#: Sampling stride of the automatic estimate: 1 pixel in 64 (36 000 at 1920x1200, plenty for two ratios).
STATS_STRIDE = 8

#: The well-exposed band the automatic estimate uses: luminance percentiles of the positive pixels.
#: Below the lower one the readings are noise-dominated; above the upper one sit light sources,
#: specular highlights and pixels that are only lower bounds (a clipped channel).
WELL_EXPOSED_PERCENTILES = (25.0, 97.0)

#: Share of the log-chromaticities dropped on each side before averaging: the interquartile mean, which a
#: strongly coloured object covering a tenth of the frame does not pull (a 20 % trim let it move 5 %).
TRIM = 0.25

#: Fewer usable pixels than this and a frame gives no estimate (the previous one is kept).
MIN_PIXELS = 64



def _numbers(value: object, what: str) -> list[float]:
    """Numbers from text (``"2,1,1.5"``, spaces, ``/`` between rows) or a (nested) sequence."""
    if isinstance(value, str):
        items = [x for x in value.replace("/", ",").replace(";", ",").replace(" ", ",").split(",") if x.strip()]
    else:
        try:
            items = list(np.asarray(value, dtype=object).reshape(-1))
        except (TypeError, ValueError):
            items = [value]
    numbers = []
    for item in items:
        if isinstance(item, bool):
            raise SveliveError(f"{what}: {item!r} is not a number")
        try:
            numbers.append(float(item))
        except (TypeError, ValueError):
            raise SveliveError(f"{what}: {item!r} is not a number") from None
    if not all(math.isfinite(x) for x in numbers):
        raise SveliveError(f"{what}: every number must be finite, got {value!r}")
    return numbers


def parse_white_balance(value: object) -> str | tuple[float, float, float]:
    """``"auto"``, or three multipliers R, G, B normalised to G = 1.

    Accepts ``"auto"``, text such as ``"2.1,1,1.6"`` or a sequence of three
    positive numbers. One-line SveliveError otherwise.
    """
    if isinstance(value, str) and value.strip().lower() == "auto":
        return "auto"
    what = "white balance (\"auto\" or three multipliers R,G,B, e.g. 2.0,1,1.5)"
    if value is None or (isinstance(value, str) and not value.strip()):
        raise SveliveError(f"{what}: got nothing")
    numbers = _numbers(value, what)
    if len(numbers) != 3:
        raise SveliveError(f"{what}: expected 3 numbers, got {len(numbers)}")
    if not all(x > 0 for x in numbers):
        raise SveliveError(f"{what}: multipliers must be > 0, got {numbers}")
    r, g, b = (x / numbers[1] for x in numbers)
    if not all(1 / MAX_MULTIPLIER <= x <= MAX_MULTIPLIER for x in (r, b)):
        raise SveliveError(f"{what}: R/G and B/G must be within 1/{MAX_MULTIPLIER:g}..{MAX_MULTIPLIER:g}, "
                           f"got {r:.4g}, {b:.4g}")
    return (r, 1.0, b)


#: Largest magnitude of a colour-matrix entry: real ones are of order 1; beyond this float32 previews overflow.
MAX_MATRIX_ENTRY = 1000.0


def _shape(value: object, what: str) -> tuple[int, ...] | None:
    """The shape of a (nested) sequence, None for text; a one-line SveliveError for rows of different lengths
    (numpy's own error for them is a paragraph, and it reached the API as a 500)."""
    if isinstance(value, str):
        return None
    try:
        return np.shape(value)
    except ValueError:
        raise SveliveError(f"{what}: rows of different lengths, got {value!r}"[:300]) from None


def parse_colour_matrix(value: object) -> tuple[float, ...] | None:
    """The camera -> linear Rec.709 matrix as 9 numbers, row-major, or None for none.

    Accepts None, ``"none"``/``""``, text of 9 numbers (``"1.6,-0.4,-0.2, ..."``,
    rows may be separated by ``/``), a flat sequence of 9 or a 3x3 nested one.
    """
    if value is None or (isinstance(value, str) and value.strip().lower() in ("", "none")):
        return None
    what = "colour matrix (9 numbers, row-major, camera RGB -> linear Rec.709, or none)"
    shape = _shape(value, what)
    if shape not in (None, (9,), (3, 3)):
        raise SveliveError(f"{what}: expected 9 numbers or 3 rows of 3, got shape {shape}")
    numbers = _numbers(value, what)
    if len(numbers) != 9:
        raise SveliveError(f"{what}: expected 9 numbers, got {len(numbers)}")
    if not all(abs(x) <= MAX_MATRIX_ENTRY for x in numbers):
        raise SveliveError(f"{what}: entries must be within +-{MAX_MATRIX_ENTRY:g} (a colour matrix's are of order 1)")
    return tuple(numbers)


@dataclass(frozen=True)
class ColourSettings:
    """How a colour frame leaves svelive.

    Attributes:
        white_balance: ``"auto"`` (estimated per frame, smoothed over time) or three
            multipliers R, G, B (normalised to G = 1; text or a sequence is accepted).
        colour_matrix: 9 numbers, row-major, from white-balanced camera RGB to linear
            Rec.709, or None. Text or a (3, 3) sequence is accepted.
        output_space: what EXR files hold, ``"camera"`` (the reconstruction as it is) or
            ``"rec709"`` (white balance and matrix applied; needs ``colour_matrix``).
    """

    white_balance: str | tuple[float, float, float] = "auto"
    colour_matrix: tuple[float, ...] | None = None
    output_space: str = "camera"

    def __post_init__(self) -> None:
        object.__setattr__(self, "white_balance", parse_white_balance(self.white_balance))
        object.__setattr__(self, "colour_matrix", parse_colour_matrix(self.colour_matrix))
        space = self.output_space.strip().lower() if isinstance(self.output_space, str) else self.output_space
        if space not in OUTPUT_SPACES:
            raise SveliveError(f"output space must be one of {', '.join(OUTPUT_SPACES)}, got {self.output_space!r}")
        object.__setattr__(self, "output_space", space)
        if space == "rec709" and self.colour_matrix is None:
            raise SveliveError("output space rec709 needs a colour matrix (camera RGB -> Rec.709): give "
                               "colour_matrix, e.g. 1,0,0,0,1,0,0,0,1 for a camera whose RGB is Rec.709 already "
                               "(the simulator's)")

    @property
    def auto(self) -> bool:
        """True when the white balance is estimated from the frames."""
        return self.white_balance == "auto"

    @property
    def matrix(self) -> np.ndarray | None:
        """The colour matrix as float64 (3, 3), or None."""
        return None if self.colour_matrix is None else np.array(self.colour_matrix, np.float64).reshape(3, 3)

    def public(self) -> dict[str, object]:
        """JSON-ready form (the names of the settings)."""
        return {"white_balance": self.white_balance if self.auto else list(self.white_balance),
                "colour_matrix": None if self.colour_matrix is None else list(self.colour_matrix),
                "output_space": self.output_space}


def _check_rgb(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3:
        raise SveliveError(f"expected an (H, W, 3) RGB image, got shape {image.shape}")
    return image


def estimate_white_balance(image: np.ndarray, valid: np.ndarray | None = None, *,
                           stride: int = STATS_STRIDE) -> np.ndarray | None:
    """Grey-world white balance of one frame from its well-exposed pixels, or None when it has too few.

    On a subsample (1 pixel in ``stride`` squared), the pixels with every channel
    positive and finite, ``valid`` where given, and luminance inside
    WELL_EXPOSED_PERCENTILES are kept; the log ratios log(R/G) and log(B/G) are
    averaged after dropping TRIM of them on each side, so strongly coloured
    objects and stray pixels do not pull the estimate. The multipliers make
    that average grey.

    Args:
        image: float (H, W, 3) linear camera RGB.
        valid: optional bool (H, W), pixels that may be used (e.g. not lower bounds).

    Returns:
        float64 (3,) multipliers R, G, B with G = 1, each within MAX_MULTIPLIER of 1.
    """
    image = _check_rgb(image)
    sample = image[::stride, ::stride]
    r, g, b = (np.asarray(sample[:, :, c], np.float32).ravel() for c in range(3))
    luminance = LUMA_WEIGHTS[0] * r + LUMA_WEIGHTS[1] * g + LUMA_WEIGHTS[2] * b
    # channels > 0 and a finite (positively weighted) sum: every channel positive and finite
    usable = (r > 0) & (g > 0) & (b > 0) & (luminance < np.inf)
    if valid is not None:
        usable &= np.asarray(valid, bool)[::stride, ::stride].ravel()
    if np.count_nonzero(usable) < MIN_PIXELS:
        return None
    # the two order statistics by two partitions of one kth each (numpy's of two kth, and np.sort, take twice as
    # long), the upper one of the top few per cent only
    ranked = luminance[usable]
    first, second = (int(p / 100 * (ranked.size - 1)) for p in WELL_EXPOSED_PERCENTILES)
    ranked = np.partition(ranked, first)
    low, high = ranked[first], order_statistic(ranked[first:], second - first)
    keep = usable & (luminance >= low) & (luminance <= high)
    n = np.count_nonzero(keep)
    if n < MIN_PIXELS:
        return None
    limit = math.log2(MAX_MULTIPLIER)
    multipliers = [1.0, 1.0, 1.0]
    cut = int(TRIM * n)
    for channel, values in ((0, r), (2, b)):
        ratio = np.log2(values[keep] / g[keep])  # log2 R/G or B/G
        # the trimmed mean, summed in sorted order: only the kept middle sorted, after one partition (0.14 ms less)
        middle = np.sort(np.partition(ratio, (cut, n - cut - 1))[cut:n - cut])
        mean = float(middle.mean())
        multipliers[channel] = 2.0 ** -min(max(mean, -limit), limit)
    return np.array(multipliers)


@dataclass(frozen=True)
class WhiteBalance:
    """The white balance in use.

    Attributes:
        multipliers: R, G, B, G = 1.
        mode: ``"auto"`` or ``"fixed"``.
        time_ns: frame time of the last frame folded in (auto), or of the frame it was asked for.
    """

    multipliers: tuple[float, float, float]
    mode: str
    time_ns: int

    def public(self) -> dict[str, object]:
        return {"mode": self.mode, "multipliers": [round(m, 6) for m in self.multipliers]}


class WhiteBalancer:
    """Stateful white balance: fixed multipliers, or the automatic estimate smoothed over frame time.

    The estimate is followed in the log domain with a first-order low-pass filter
    of time constant ``adapt_s`` seconds of frame time (slower than the tone
    mapper's exposure: a colour cast that drifts with noise is more visible than
    a brightness that does). A frame is measured only when ``measure_s`` of frame
    time have passed since the last measurement (the filter's weight accounts for
    the interval), so at 30 fps every third frame pays for an estimate. A frame more
    than ``reset_after_s`` after the previous measurement restarts it. Not
    thread-safe: one thread updates it; ``current`` (an immutable record) may be
    read from any thread.
    """

    def __init__(self, settings: ColourSettings | None = None, adapt_s: float = 1.0, measure_s: float = 0.09,
                 reset_after_s: float = 2.0) -> None:
        self.settings = settings or ColourSettings()
        self.adapt_s = adapt_s
        self.measure_s = measure_s
        self.reset_after_s = reset_after_s
        self.current: WhiteBalance | None = None

    def configure(self, settings: ColourSettings) -> None:
        """Use new settings from the next frame on (a switch back to auto starts from the next frame's estimate)."""
        if settings.auto and not self.settings.auto:
            self.current = None
        self.settings = settings

    def update(self, image: np.ndarray, time_ns: int, valid: np.ndarray | None = None) -> WhiteBalance:
        """Fold one frame (float (H, W, 3) camera RGB, frame time in ns) in; returns the white balance to use."""
        if not self.settings.auto:
            self.current = WhiteBalance(self.settings.white_balance, "fixed", time_ns)  # type: ignore[arg-type]
            return self.current
        previous = self.current if self.current is not None and self.current.mode == "auto" else None
        dt = None if previous is None else (time_ns - previous.time_ns) / 1e9
        if previous is not None and 0 <= dt < self.measure_s:
            return previous
        measured = estimate_white_balance(image, valid)
        if measured is None:
            kept = previous.multipliers if previous is not None else (1.0, 1.0, 1.0)
            self.current = WhiteBalance(kept, "auto", time_ns)
            return self.current
        if previous is not None and 0 <= dt <= self.reset_after_s:
            alpha = smoothing_factor(dt, self.adapt_s)
            old = np.log2(previous.multipliers)
            measured = np.exp2(old + alpha * (np.log2(measured) - old))
        self.current = WhiteBalance((float(measured[0]), 1.0, float(measured[2])), "auto", time_ns)
        return self.current

    def for_frame(self, image: np.ndarray, time_ns: int, settings: ColourSettings | None = None) -> WhiteBalance:
        """The white balance for one frame without changing the state (e.g. an EXR snapshot off the updating thread).

        Fixed: the fixed multipliers. Auto: the smoothed state when it is recent
        (within ``reset_after_s`` of ``time_ns``), so a snapshot matches the preview;
        else this frame's own estimate. ``settings``: these instead of the last configured ones.
        """
        settings = settings or self.settings
        if not settings.auto:
            return WhiteBalance(settings.white_balance, "fixed", time_ns)  # type: ignore[arg-type]
        current = self.current
        if current is not None and current.mode == "auto" and abs(time_ns - current.time_ns) <= self.reset_after_s * 1e9:
            return current
        measured = estimate_white_balance(image)
        multipliers = (1.0, 1.0, 1.0) if measured is None else (float(measured[0]), 1.0, float(measured[2]))
        return WhiteBalance(multipliers, "auto", time_ns)


def output_matrix(multipliers: Sequence[float], matrix: np.ndarray | Sequence[float] | None = None) -> np.ndarray:
    """float32 (3, 3): camera RGB -> output, ``M @ diag(multipliers)`` (just the diagonal without ``M``)."""
    out = np.diag(np.asarray(multipliers, np.float64))
    if matrix is not None:
        out = np.asarray(matrix, np.float64).reshape(3, 3) @ out
    return out.astype(np.float32)


def apply_matrix(image: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """``matrix`` (3, 3) applied to every pixel of float (H, W, 3): float32 (H, W, 3), one pass."""
    image = _check_rgb(image)
    return cv2.transform(np.ascontiguousarray(image, dtype=np.float32), np.asarray(matrix, np.float32).reshape(3, 3))


def to_output_space(image: np.ndarray, balance: WhiteBalance | Sequence[float], settings: ColourSettings) -> np.ndarray:
    """What an EXR holds of a camera-RGB frame: ``image`` itself in the camera space, else M @ diag(wb) applied.

    Args:
        image: float32 (H, W, 3) linear camera RGB.
        balance: the white balance in use (a WhiteBalance or the three multipliers).
        settings: ``output_space`` and ``colour_matrix``.

    Returns:
        float32 (H, W, 3) in ``settings.output_space``.
    """
    image = _check_rgb(image)
    if settings.output_space == "camera":
        return image
    multipliers = balance.multipliers if isinstance(balance, WhiteBalance) else tuple(balance)
    return apply_matrix(image, output_matrix(multipliers, settings.matrix))


def exr_attributes(balance: WhiteBalance | Sequence[float], settings: ColourSettings,
                   mode: str | None = None) -> dict[str, object]:
    """EXR header attributes saying what the R, G, B of :func:`to_output_space` are.

    ``colourSpace`` (``"camera"`` or ``"rec709"``); ``whiteBalance`` (V3f, the
    multipliers in use), ``whiteBalanceMode`` (``"auto"``/``"fixed"``) and
    ``whiteBalanceApplied`` (1 when the data has it, i.e. rec709); for rec709 also
    ``colourMatrix`` (M33f) and the standard ``chromaticities`` (Rec. 709 primaries,
    D65 white). Camera RGB has no chromaticities: its primaries are the sensor's
    own, unknown here (readers that assume Rec. 709 without the attribute show it
    as if it were).
    """
    if isinstance(balance, WhiteBalance):
        multipliers, mode = balance.multipliers, balance.mode
    else:
        multipliers, mode = tuple(balance), mode or ("auto" if settings.auto else "fixed")
    applied = settings.output_space == "rec709"
    out: dict[str, object] = {"colourSpace": settings.output_space,
                              "whiteBalance": np.array(multipliers, np.float32),
                              "whiteBalanceMode": mode, "whiteBalanceApplied": int(applied)}
    if applied:
        out["colourMatrix"] = settings.matrix.astype(np.float32)  # type: ignore[union-attr]
        out["chromaticities"] = REC709_CHROMATICITIES
    return out


def exr_output(image: np.ndarray, balance: WhiteBalance | None, settings: ColourSettings
               ) -> tuple[dict[str, np.ndarray], dict[str, object]]:
    """EXR channels and colour attributes of a reconstructed frame.

    A mono (H, W) frame gives ``Y`` and no attributes; a colour (H, W, 3) one ``R``, ``G``,
    ``B`` in ``settings.output_space`` (:func:`to_output_space`) and :func:`exr_attributes`.
    """
    if image.ndim == 2:
        return image_channels(image), {}
    if balance is None:
        raise SveliveError("a colour frame needs its white balance for the EXR (WhiteBalancer.update)")
    return image_channels(to_output_space(image, balance, settings)), exr_attributes(balance, settings)
