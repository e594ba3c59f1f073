"""The sensor: bit depth, black and white level, and its Poisson-Gaussian noise model.

Units: signals are in DN above black (``raw - black``); radiance in the project's
output unit, DN at relative exposure 1 (see docs/method-notes). The noise model
is the one of the method notes: a pixel of exposure e seeing radiance L collects
Poisson(g e L) electrons (g = electrons per DN) plus Gaussian read noise of
``read_noise`` DN, then is quantised.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from svelive.core.errors import SveliveError

#: Variance of rounding to integer DN (uniform quantisation), DN^2: the least signal-independent noise a
#: reading has.
QUANTISATION_VARIANCE = 1.0 / 12.0

#: Assumed when the datasheet values are unknown: a 10 000 e- full well and 3 e-
#: read noise, typical of machine-vision CMOS. Inverse-variance weights depend only
#: on the ratio of shot to read noise, so these only shape the weights, never
#: the scale of the result.
DEFAULT_FULL_WELL_E = 10_000.0
DEFAULT_READ_NOISE_E = 3.0


def container_bits(dtype: np.dtype) -> int:
    """Bit depth a raw array's dtype implies when nothing else says: 8 for uint8, else 16."""
    return 8 if np.dtype(dtype) == np.uint8 else 16


@dataclass(frozen=True)
class Sensor:
    """Static description of a sensor.

    Attributes:
        bits: bit depth of the raw values (1..16).
        black_level: raw value of no light, DN.
        white_level: raw value at or above which a pixel is saturated, DN
            (default 2**bits - 1).
        gain: electrons per DN; None means "unknown", use the default full well.
        read_noise: read noise in DN (standard deviation); None means unknown.
    """

    bits: int = 12
    black_level: float = 0.0
    white_level: float | None = None
    gain: float | None = None
    read_noise: float | None = None

    def __post_init__(self) -> None:
        if not 1 <= int(self.bits) <= 16:
            raise SveliveError(f"bit depth must be 1..16, got {self.bits}")
        white = float(2 ** int(self.bits) - 1) if self.white_level is None else float(self.white_level)
        object.__setattr__(self, "white_level", white)
        if not np.isfinite(self.black_level) or self.black_level < 0:
            raise SveliveError(f"black level must be >= 0, got {self.black_level}")
        if not self.black_level < white:
            raise SveliveError(f"black level {self.black_level:g} must be below the white level {white:g}")
        if self.gain is not None and not self.gain > 0:
            raise SveliveError(f"gain (electrons per DN) must be > 0, got {self.gain}")
        if self.read_noise is not None and not self.read_noise >= 0:
            raise SveliveError(f"read noise must be >= 0 DN, got {self.read_noise}")

    @classmethod
    def from_full_well(cls, bits: int, full_well_e: float, read_noise_e: float,
                       black_level: float = 0.0, white_level: float | None = None) -> Sensor:
        """A sensor described the datasheet way: full-well capacity and read noise in electrons."""
        white = float(2**bits - 1) if white_level is None else float(white_level)
        gain = full_well_e / (white - black_level)
        return cls(bits, black_level, white, gain, read_noise_e / gain)

    def with_noise(self, gain: float | None = None, read_noise: float | None = None) -> Sensor:
        """This sensor with ``gain`` and ``read_noise`` where given (None keeps the sensor's own)."""
        return replace(self, gain=self.gain if gain is None else gain,
                       read_noise=self.read_noise if read_noise is None else read_noise)

    @property
    def range_dn(self) -> float:
        """Usable signal range above black, DN."""
        return float(self.white_level) - float(self.black_level)

    @property
    def effective_gain(self) -> float:
        """Electrons per DN, the default full well assumed when unknown."""
        return self.gain if self.gain is not None else DEFAULT_FULL_WELL_E / self.range_dn

    @property
    def effective_read_noise(self) -> float:
        """Read noise in DN, the default assumed when unknown."""
        return self.read_noise if self.read_noise is not None else DEFAULT_READ_NOISE_E / self.effective_gain

    @property
    def floor_variance(self) -> float:
        """Signal-independent variance, DN^2: read noise plus uniform quantisation (1/12)."""
        return self.effective_read_noise**2 + QUANTISATION_VARIANCE

    def signal_variance(self, signal_dn: np.ndarray | float) -> np.ndarray | float:
        """Variance of a raw reading (DN^2) whose expected signal above black is ``signal_dn``."""
        return np.maximum(signal_dn, 0) / self.effective_gain + self.floor_variance

    @property
    def censor_level(self) -> float:
        """Signal above black (DN) at or above which a reading is censored ("at least this").

        Readings within two noise standard deviations of white are censored too: a
        pixel whose mean lies there is clipped often, so the ones that survive are
        biased low.
        """
        sigma_white = float(np.sqrt(self.signal_variance(self.range_dn)))
        return max(self.range_dn - 2.0 * sigma_white, 0.5 * self.range_dn)
