"""Known response curves (:data:`CURVES`), for simulating non-linear cameras (:func:`simulate_nonlinear`):
the tests' and benchmarks' ground truth."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from numpy.polynomial import polynomial as P

from svelive.core.pattern import Pattern
from svelive.core.sensor import Sensor
from svelive.simulation import simulate


@dataclass(frozen=True)
class ResponseCurve:
    """A known camera response: ``forward`` maps linear I in [0, 1] to brightness M in [0, 1],
    ``inverse`` maps back; both increasing with f(0) = 0, f(1) = 1."""

    name: str
    forward: Callable[[np.ndarray], np.ndarray]
    inverse: Callable[[np.ndarray], np.ndarray]


def _bisect_inverse(forward: Callable[[np.ndarray], np.ndarray]) -> Callable[[np.ndarray], np.ndarray]:
    grid = np.linspace(0.0, 1.0, 20001)
    values = forward(grid)
    return lambda m: np.interp(m, values, grid)


#: Inverse of the "polynomial" camera: I = 0.1 M + 0.3 M^2 + 0.6 M^3.
POLY3 = (0.0, 0.1, 0.3, 0.6)


def _s_curve(i: np.ndarray) -> np.ndarray:
    # film-like: flat toe and shoulder, steep middle; monotone since 0.6 < 1
    return i - 0.6 * np.sin(2 * np.pi * i) / (2 * np.pi)


CURVES: dict[str, ResponseCurve] = {
    "linear": ResponseCurve("linear", lambda i: np.asarray(i, np.float64), lambda m: np.asarray(m, np.float64)),
    "gamma2.2": ResponseCurve("gamma2.2", lambda i: np.power(np.clip(i, 0, 1), 1 / 2.2),
                              lambda m: np.power(np.clip(m, 0, 1), 2.2)),
    "poly3": ResponseCurve("poly3", _bisect_inverse(lambda m: P.polyval(m, POLY3)),
                           lambda m: P.polyval(np.asarray(m, np.float64), POLY3)),
    "s-curve": ResponseCurve("s-curve", _s_curve, _bisect_inverse(_s_curve)),
}


def simulate_nonlinear(radiance: np.ndarray, pattern: Pattern | str, sensor: Sensor, curve: ResponseCurve, *,
                       seed: int = 0) -> np.ndarray:
    """Raw SVE frame of a camera with response ``curve``, uint8/uint16 (H, W).

    The light is collected and made noisy linearly (the sensor's gain and read
    noise, :func:`svelive.simulation.simulate` at 16 bits of the same full well),
    then the response maps it to brightness and the ADC quantises to the
    sensor's bits.

    Args:
        radiance: float (H, W), radiance in DN (of ``sensor``) at exposure 1.
    """
    full_well = sensor.effective_gain * sensor.range_dn
    read_e = sensor.effective_read_noise * sensor.effective_gain
    fine = Sensor.from_full_well(16, full_well, read_e)
    scale = fine.range_dn / sensor.range_dn
    linear = simulate(np.asarray(radiance, np.float32) * scale, pattern, fine, seed=seed).raw
    m = curve.forward(np.clip(linear / fine.range_dn, 0.0, 1.0))
    dn = np.rint(float(sensor.black_level) + m * sensor.range_dn)
    dtype = np.uint8 if sensor.bits <= 8 else np.uint16
    return np.clip(dn, 0, sensor.white_level).astype(dtype)
