"""Preview tone mapping: a global operator whose statistics are smoothed over time.

Per-frame operators (OpenCV's included) normalise every frame by its own
statistics, so sensor noise and small scene changes make the preview flicker.
Here the two statistics of Reinhard's global operator, the key (log-average
radiance) and the white point (a high percentile), are measured on a subsample
of each frame and followed with a first-order low-pass filter in the log
domain whose time constant is ``adapt_s`` seconds of frame time:

    s_t = s_{t-1} + (1 - exp(-dt / adapt_s)) (m_t - s_{t-1})

so a static scene keeps a steady curve (noise in the statistics is averaged
over about ``adapt_s`` seconds of frames) and a step in illumination is
followed to within exp(-1 / adapt_s) of its size after one second (0.7 % of
the step in log radiance at the default 0.2 s).

The curve is Reinhard's extended operator with the white point burning out,
then the sRGB transfer function. Being global, it is applied through a
lookup table indexed by the top 17 bits of the float32 radiance (sign,
exponent and 8 mantissa bits: steps of 0.4 % in radiance, below one display
code value): one shift and one table lookup per pixel, about 1 ms for
1920x1200 on one core.

Colour frames (H, W, 3) are first taken to linear display RGB (Rec. 709 / sRGB
primaries) by a 3x3 matrix the caller gives (white balance and the camera
matrix, svelive.whitebalance.output_matrix); the statistics and the curve act
on their luminance, and every channel is scaled by the curve's gain at that
luminance, so channel ratios (hue and saturation) are kept. Where that puts a
channel above :data:`KNEE` the pixel is desaturated towards the grey of its own
display luminance, just enough that the largest channel approaches 1 softly
(and a channel a matrix made negative reaches 0): over-range highlights turn
white with their luminance intact instead of clipping one channel at a time,
which shifts hue (magenta, yellow) and posterises. One compiled pass, blocks of
:data:`BLOCK` pixels: the arithmetic vectorised into a small buffer, then the sRGB
table per channel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from svelive.core.errors import SveliveError
from svelive.core.order import percentile
from svelive.exr import LUMA_WEIGHTS
from svelive.jit import flat, fma32, kernel

#: Sampling stride of the statistics: 1 pixel in 16 is plenty for two global numbers.
STATS_STRIDE = 4

#: Low bits of a float32 dropped to index the curve table (23 mantissa bits - 15 = 8 kept).
LUT_SHIFT = 15
LUT_SIZE = 1 << (32 - LUT_SHIFT)

#: Display-linear level above which a colour pixel's largest channel is compressed softly towards 1.
KNEE = 0.8

#: Pixels per block of the colour kernel (its buffer, 3 KiB, stays in the L1 cache).
BLOCK = 256


@dataclass(frozen=True)
class ToneSettings:
    """Parameters of the preview operator.

    Attributes:
        exposure_ev: exposure compensation in stops (added to the automatic exposure).
        key: middle-grey target of the log-average radiance (Reinhard's a), in (0, 1).
        white_percentile: percentile of radiance mapped to display white, in [50, 100].
        adapt_s: time constant of the temporal smoothing in seconds of frame time;
            0 follows every frame's own statistics.
    """

    exposure_ev: float = 0.0
    key: float = 0.18
    white_percentile: float = 99.5
    adapt_s: float = 0.2

    def __post_init__(self) -> None:
        checks = (
            ("exposure_ev", -16.0 <= self.exposure_ev <= 16.0, "-16..16 stops"),
            ("key", 0.01 <= self.key <= 0.9, "0.01..0.9"),
            ("white_percentile", 50.0 <= self.white_percentile <= 100.0, "50..100"),
            ("adapt_s", 0.0 <= self.adapt_s <= 60.0, "0..60 s"),
        )
        for name, ok, allowed in checks:
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and ok):
                raise SveliveError(f"tone mapping {name} must be in {allowed}, got {value!r}")


@dataclass(frozen=True)
class ToneStats:
    """The smoothed statistics the curve is built from, log2 of radiance (DN at exposure 1)."""

    log2_average: float
    log2_white: float
    time_ns: int


def luminance_weights(matrix: np.ndarray | None = None) -> np.ndarray:
    """float32 (3,): display luminance of an image's channels, Rec. 709 weights after ``matrix`` (3, 3) if given."""
    weights = np.asarray(LUMA_WEIGHTS, np.float64)
    if matrix is not None:
        weights = weights @ check_matrix(matrix)
    return weights.astype(np.float32)


def check_matrix(matrix: np.ndarray) -> np.ndarray:
    """``matrix`` as float64 (3, 3); a one-line error unless it is 3x3 and finite."""
    matrix = np.asarray(matrix, np.float64)
    if matrix.shape != (3, 3) or not np.all(np.isfinite(matrix)):
        raise SveliveError(f"display matrix must be 3x3 and finite, got shape {matrix.shape}")
    return matrix


def frame_statistics(image: np.ndarray, white_percentile: float,
                     matrix: np.ndarray | None = None) -> tuple[float, float] | None:
    """(log2 log-average, log2 white point) of the positive radiance of ``image``.

    Args:
        image: float32 (H, W) radiance, >= 0, or (H, W, 3) colour, whose display
            luminance (:func:`luminance_weights` of ``matrix``) is measured.
        white_percentile: the percentile taken as the white point.
        matrix: for colour, (3, 3) from the image's channels to linear display RGB; None: identity.

    Returns:
        The two statistics, or None when the frame has no positive pixel.
    """
    sample = image[::STATS_STRIDE, ::STATS_STRIDE]
    if sample.ndim == 3:
        sample = sample @ luminance_weights(matrix)
    positive = sample[sample > 0]
    if positive.size == 0:
        return None
    logs = np.log2(positive)
    log_avg = float(logs.mean())
    log_white = percentile(logs, white_percentile)  # (np.percentile's, faster)
    return log_avg, max(log_white, log_avg)



def smoothing_factor(dt_s: float, adapt_s: float) -> float:
    """Weight of the new measurement for a frame ``dt_s`` seconds after the last one."""
    if adapt_s <= 0:
        return 1.0
    return 1.0 - math.exp(-max(dt_s, 0.0) / adapt_s)


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """sRGB transfer function of display-linear values (float array of any shape, clipped to [0, 1])."""
    linear = np.clip(linear, 0.0, 1.0)
    return np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * np.power(linear, 1 / 2.4) - 0.055)


@lru_cache(maxsize=1)
def _bin_radiance() -> np.ndarray:
    """Radiance at the middle of every positive finite LUT bin, float32 (n,), read-only."""
    index = np.arange(LUT_SIZE // 2, dtype=np.uint32)
    centres = ((index << LUT_SHIFT) | np.uint32(1 << (LUT_SHIFT - 1))).view(np.float32)
    centres = centres[np.isfinite(centres)].copy()
    centres.setflags(write=False)
    return centres


def curve_constants(stats: ToneStats, settings: ToneSettings) -> tuple[np.float32, np.float32]:
    """(scale, 1 / white^2) of the curve: y = scale * radiance is displayed as y (1 + y / white^2) / (1 + y)."""
    scale = np.float32(settings.key * 2.0 ** (settings.exposure_ev - stats.log2_average))
    y_white = max(settings.key * 2.0 ** (stats.log2_white - stats.log2_average), 1e-6)
    return scale, np.float32(1.0 / (y_white * y_white))


@lru_cache(maxsize=1)
def srgb_lut() -> np.ndarray:
    """uint8 sRGB code of display-linear values, LUT_SIZE entries indexed by ``float32 bits >> LUT_SHIFT``, read-only.

    Negative bins give 0; values at or above 1, +inf and positive NaNs give 255.
    """
    radiance = _bin_radiance()
    lut = np.zeros(LUT_SIZE, np.uint8)
    lut[:radiance.size] = np.rint(srgb_encode(radiance) * 255)
    lut[radiance.size:LUT_SIZE // 2] = 255
    lut.setflags(write=False)
    return lut


def curve_lut(stats: ToneStats, settings: ToneSettings) -> np.ndarray:
    """The display curve as a uint8 table of LUT_SIZE entries indexed by ``float32 bits >> LUT_SHIFT``.

    Entry i holds the display value of the radiance in the middle of its bin;
    negative bins map to 0, the bin of +inf (and positive NaNs) to 255.
    """
    radiance = _bin_radiance()
    scale, inverse_white2 = curve_constants(stats, settings)
    y = radiance * scale
    with np.errstate(over="ignore", invalid="ignore"):
        display = y * (1 + y * inverse_white2) / (1 + y)
    display[~np.isfinite(display)] = 1.0  # y overflowed: far above white
    lut = np.zeros(LUT_SIZE, np.uint8)
    lut[:radiance.size] = np.rint(srgb_encode(display) * 255)
    lut[radiance.size:LUT_SIZE // 2] = 255
    return lut


class ToneMapper:
    """Stateful preview operator: ``update`` the statistics with each new frame, ``apply`` the curve.

    Not thread-safe: one encoder thread owns it. ``reset_after_s``: a frame this
    long after the previous one restarts the smoothing (the scene may have changed
    completely while nobody watched).
    """

    def __init__(self, settings: ToneSettings | None = None, reset_after_s: float = 2.0) -> None:
        self.settings = settings or ToneSettings()
        self.reset_after_s = reset_after_s
        self.stats: ToneStats | None = None
        self._lut: np.ndarray | None = None
        self._lut_key: tuple | None = None

    def configure(self, settings: ToneSettings) -> None:
        """Use new parameters from the next frame on; the smoothed statistics are kept."""
        self.settings = settings

    def update(self, image: np.ndarray, time_ns: int, matrix: np.ndarray | None = None) -> ToneStats:
        """Fold one frame's statistics into the smoothed ones.

        Args:
            image: float32 (H, W) radiance, or (H, W, 3) colour.
            time_ns: the frame's time.
            matrix: for colour, (3, 3) from the image's channels to linear display RGB (None: identity).
        """
        measured = frame_statistics(image, self.settings.white_percentile, matrix)
        previous = self.stats
        if measured is None:
            if previous is None:
                self.stats = ToneStats(0.0, 0.0, time_ns)
            return self.stats
        dt = None if previous is None else (time_ns - previous.time_ns) / 1e9
        if dt is None or dt < 0 or dt > self.reset_after_s:
            alpha = 1.0
        else:
            alpha = smoothing_factor(dt, self.settings.adapt_s)
        if previous is None:
            self.stats = ToneStats(measured[0], measured[1], time_ns)
        else:
            self.stats = ToneStats(previous.log2_average + alpha * (measured[0] - previous.log2_average),
                                   previous.log2_white + alpha * (measured[1] - previous.log2_white),
                                   time_ns)
        return self.stats

    def lut(self) -> np.ndarray:
        """The current curve (see :func:`curve_lut`), rebuilt only when statistics or settings change."""
        if self.stats is None:
            raise SveliveError("tone mapper has no statistics yet; call update() first")
        key = (self.stats.log2_average, self.stats.log2_white, self.settings)
        if key != self._lut_key:
            self._lut = curve_lut(self.stats, self.settings)
            self._lut_key = key
        return self._lut

    def apply(self, image: np.ndarray, matrix: np.ndarray | None = None, *, bgr: bool = False) -> np.ndarray:
        """Display image through the current curve.

        Args:
            image: float32 (H, W) radiance, or (H, W, 3) colour.
            matrix: for colour, (3, 3) from the image's channels to linear display RGB
                (Rec. 709 primaries; white balance included); None: identity.
            bgr: for colour, write the channels in B, G, R order (OpenCV's).

        Returns:
            uint8 sRGB, (H, W) for a mono image, (H, W, 3) (RGB, or BGR) for colour.
        """
        if self.stats is None:
            raise SveliveError("tone mapper has no statistics yet; call update() first")
        image = np.ascontiguousarray(image, dtype=np.float32)
        display = np.empty(image.shape, np.uint8)
        if image.ndim == 2:
            if matrix is not None:
                raise SveliveError("a display matrix applies to colour (H, W, 3) images, not to a mono one")
            _look_up(*flat(image.view(np.uint32), display), self.lut(), LUT_SHIFT)
            return display
        if image.ndim != 3 or image.shape[2] != 3:
            raise SveliveError(f"tone mapping takes (H, W) or (H, W, 3) images, got shape {image.shape}")
        a = np.eye(3) if matrix is None else check_matrix(matrix)
        luma = np.float32(LUMA_WEIGHTS)
        if bgr:  # the kernel writes its rows in order: reverse them, and the weights that follow them
            a, luma = a[::-1], luma[::-1]
        scale, inverse_white2 = curve_constants(self.stats, self.settings)
        _tone_colour(*flat(image, display), np.ascontiguousarray(a, np.float32).reshape(-1),
                     np.ascontiguousarray(luma), scale, inverse_white2, np.float32(KNEE), srgb_lut(), LUT_SHIFT)
        return display

    def __call__(self, image: np.ndarray, time_ns: int, matrix: np.ndarray | None = None, *,
                 bgr: bool = False) -> np.ndarray:
        """Update with ``image`` then map it (see :meth:`update` and :meth:`apply`)."""
        self.update(image, time_ns, matrix)
        return self.apply(image, matrix, bgr=bgr)


@kernel
def _look_up(bits: np.ndarray, display: np.ndarray, lut: np.ndarray, shift: int) -> None:
    """display[i] = lut[bits[i] >> shift]: the curve applied in one pass (a shift then np.take makes two)."""
    for i in range(bits.size):
        display[i] = lut[bits[i] >> shift]


@kernel
def _tone_colour(pixels: np.ndarray, display: np.ndarray, a: np.ndarray, luma: np.ndarray, scale: np.float32,
                 inverse_white2: np.float32, knee: np.float32, lut: np.ndarray, shift: int) -> None:
    """The colour preview of interleaved RGB ``pixels`` (float32 (3 N,)) into ``display`` (uint8 (3 N,)).

    Per pixel: c = a c (a: (9,) row-major, to display RGB, or BGR with its rows and ``luma``
    reversed); luminance L = luma . c;
    c *= g(L), the curve's gain display(L) / L; then, where the largest channel
    exceeds ``knee`` or the smallest is negative, c moves towards the grey
    level g(L) L (luminance kept) until the largest is knee + (1 - knee) t / (1 + t),
    t = (max - knee) / (1 - knee) (a soft shoulder with slope 1 at the knee and 1
    as its limit) and the smallest >= 0; then sRGB through ``lut``. Branch-free,
    in blocks of BLOCK pixels: the arithmetic vectorises into a small buffer,
    then one table lookup per value.
    """
    a0, a1, a2, a3, a4, a5, a6, a7, a8 = a[0], a[1], a[2], a[3], a[4], a[5], a[6], a[7], a[8]
    w0, w1, w2 = luma[0], luma[1], luma[2]
    one, zero, tiny = np.float32(1.0), np.float32(0.0), np.float32(1e-12)
    span = one - knee
    n = pixels.size // 3
    buffer = np.empty(3 * BLOCK, np.float32)
    bits = buffer.view(np.uint32)
    for start in range(0, n, BLOCK):
        m = min(BLOCK, n - start)
        block = pixels[3 * start:3 * (start + m)]
        out = display[3 * start:3 * (start + m)]
        for j in range(m):
            r = block[3 * j]
            g = block[3 * j + 1]
            b = block[3 * j + 2]
            x = fma32(a2, b, fma32(a1, g, a0 * r))
            y = fma32(a5, b, fma32(a4, g, a3 * r))
            z = fma32(a8, b, fma32(a7, g, a6 * r))
            lum = fma32(w1, y, fma32(w2, z, w0 * x))  # the same sum in BGR order, where x and z swap
            lum = lum if lum > zero else zero
            yk = lum * scale
            gain = scale * (one + yk * inverse_white2) / (one + yk)
            grey = lum * gain
            x *= gain
            y *= gain
            z *= gain
            hi = x if x > y else y
            hi = hi if hi > z else z
            lo = x if x < y else y
            lo = lo if lo < z else z
            # the shoulder's target, knee + span u / (span + u), u = max(hi - knee, 0), is a fraction whose
            # denominator joins the others': s = min((target - grey) / spread, 1, grey / below), at least 0,
            # with one division instead of four
            u = hi - knee
            u = u if u > zero else zero
            d = span + u
            above = (knee - grey) * d + span * u  # (target - grey) d, before the target is clamped to [grey, hi]
            spread = hi - grey
            spread = (spread if spread > tiny else tiny) * d
            below = grey - lo
            below = below if below > tiny else tiny
            s = above * below
            s = s if s < spread * below else spread * below
            s = s if s < grey * spread else grey * spread
            s = (s if s > zero else zero) / (spread * below)
            buffer[3 * j] = fma32(s, x - grey, grey)
            buffer[3 * j + 1] = fma32(s, y - grey, grey)
            buffer[3 * j + 2] = fma32(s, z - grey, grey)
        for j in range(3 * m):
            out[j] = lut[bits[j] >> shift]


def warm_up() -> None:
    """Compile, or load from numba's disk cache, the preview kernels (mono and colour) on tiny frames."""
    rng = np.random.default_rng(0)
    mono = rng.uniform(0, 100, (8, 8)).astype(np.float32)
    ToneMapper()(mono, 0)
    ToneMapper()(np.dstack([mono, mono, mono]), 0, np.eye(3), bgr=True)
