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
code value): one shift and one table lookup per pixel, about 3 ms for
1920x1200 on one core.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from svelive.errors import SveliveError
from svelive.jit import flat, kernel

#: Sampling stride of the statistics: 1 pixel in 16 is plenty for two global numbers.
STATS_STRIDE = 4

#: Low bits of a float32 dropped to index the curve table (23 mantissa bits - 15 = 8 kept).
LUT_SHIFT = 15
LUT_SIZE = 1 << (32 - LUT_SHIFT)


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


def frame_statistics(image: np.ndarray, white_percentile: float) -> tuple[float, float] | None:
    """(log2 log-average, log2 white point) of the positive radiance of ``image``.

    Args:
        image: float32 (H, W) radiance, >= 0.
        white_percentile: the percentile taken as the white point.

    Returns:
        The two statistics, or None when the frame has no positive pixel.
    """
    sample = image[::STATS_STRIDE, ::STATS_STRIDE]
    positive = sample[sample > 0]
    if positive.size == 0:
        return None
    logs = np.log2(positive)
    log_avg = float(logs.mean())
    log_white = float(np.percentile(logs, white_percentile))
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


def curve_lut(stats: ToneStats, settings: ToneSettings) -> np.ndarray:
    """The display curve as a uint8 table of LUT_SIZE entries indexed by ``float32 bits >> LUT_SHIFT``.

    Entry i holds the display value of the radiance in the middle of its bin;
    negative bins map to 0, the bin of +inf (and positive NaNs) to 255.
    """
    radiance = _bin_radiance()
    y = radiance * np.float32(settings.key * 2.0 ** (settings.exposure_ev - stats.log2_average))
    y_white = max(settings.key * 2.0 ** (stats.log2_white - stats.log2_average), 1e-6)
    with np.errstate(over="ignore", invalid="ignore"):
        display = y * (1 + y * np.float32(1.0 / (y_white * y_white))) / (1 + y)
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

    def update(self, image: np.ndarray, time_ns: int) -> ToneStats:
        """Fold one frame's statistics (float32 (H, W) radiance, frame time in ns) into the smoothed ones."""
        measured = frame_statistics(image, self.settings.white_percentile)
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

    def apply(self, image: np.ndarray) -> np.ndarray:
        """Display image, uint8 (H, W), of float32 (H, W) radiance through the current curve."""
        if self.stats is None:
            raise SveliveError("tone mapper has no statistics yet; call update() first")
        image = np.ascontiguousarray(image, dtype=np.float32)
        display = np.empty(image.shape, np.uint8)
        _look_up(*flat(image.view(np.uint32), display), self.lut(), LUT_SHIFT)
        return display

    def __call__(self, image: np.ndarray, time_ns: int) -> np.ndarray:
        """Update with ``image`` then map it: uint8 (H, W)."""
        self.update(image, time_ns)
        return self.apply(image)


@kernel
def _look_up(bits: np.ndarray, display: np.ndarray, lut: np.ndarray, shift: int) -> None:
    """display[i] = lut[bits[i] >> shift]: the curve applied in one pass (a shift then np.take makes two)."""
    for i in range(bits.size):
        display[i] = lut[bits[i] >> shift]
