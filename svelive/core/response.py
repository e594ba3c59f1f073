"""The camera's inverse response ``I = f(M)`` as a value (:class:`Response`) and its use on raw frames
(:func:`linearise`); fitting one from frames is svelive.calibrate.response's job."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.polynomial import polynomial as P

from svelive.core.errors import SveliveError
from svelive.core.sensor import Sensor


@dataclass(frozen=True)
class Response:
    """A fitted inverse response ``I = f(M)``, normalised by f(1) = 1.

    Two forms:

    - polynomial (``knots`` empty): ``f(M) = sum c_n M^n``, ``coefficients`` c_0 first;
    - log-spline (``knots`` given): ``log f(M) = c_0 + c_1 u + sum_j c_(j+2) x_j(u)`` in
      ``u = log M``, with ``x_j`` the restricted (natural) cubic spline basis on the knots
      (:func:`log_spline_basis`): a power law ``f = e^c_0 M^c_1`` below the first knot and
      above the last, cubic in ``u`` between them. ``f(0) = 0``.

    Attributes:
        coefficients: see above.
        domain: (low, high) brightness range the curve takes; inputs are clipped to it.
        black_level, white_level: DN; M = (raw - black) / (white - black).
        stats: fit statistics (measured range, samples, held-out errors per model, ...).
        knots: brightness M of the log-spline's knots, increasing, in (0, 1]; empty for a polynomial.
    """

    coefficients: tuple[float, ...]
    domain: tuple[float, float] = (0.0, 1.0)
    black_level: float = 0.0
    white_level: float = 255.0
    stats: dict = field(default_factory=dict, compare=False)
    knots: tuple[float, ...] = ()

    @property
    def model(self) -> str:
        """``"polynomial"`` or ``"log-spline"``."""
        return "log-spline" if self.knots else "polynomial"

    @property
    def degree(self) -> int:
        """The polynomial's degree; for a log-spline the degree of its pieces in log M (3)."""
        return 3 if self.knots else len(self.coefficients) - 1

    def __call__(self, brightness: np.ndarray | float) -> np.ndarray:
        """Linear radiance I (float64, f(1) = 1) of normalised brightness M."""
        m = np.clip(np.asarray(brightness, dtype=np.float64), *self.domain)
        if not self.knots:
            return P.polyval(m, np.asarray(self.coefficients))
        return _log_spline_value(np.asarray(self.coefficients), np.log(self.knots), m)[0]

    def slope(self, brightness: np.ndarray | float) -> np.ndarray:
        """dI/dM (float64) at normalised brightness M (clipped to the domain)."""
        m = np.clip(np.asarray(brightness, dtype=np.float64), *self.domain)
        if not self.knots:
            return P.polyval(m, P.polyder(np.asarray(self.coefficients)))
        return _log_spline_value(np.asarray(self.coefficients), np.log(self.knots), m)[1]

    def to_dict(self) -> dict:
        data = {"degree": self.degree, "coefficients": list(self.coefficients), "domain": list(self.domain),
                "black_level": self.black_level, "white_level": self.white_level, "stats": self.stats}
        if self.knots:
            data["model"] = self.model
            data["knots"] = list(self.knots)
        return data

    @classmethod
    def from_dict(cls, data: dict) -> Response:
        try:
            coefficients = tuple(float(c) for c in data["coefficients"])
            domain = tuple(float(d) for d in data.get("domain", (0.0, 1.0)))
            black = float(data.get("black_level", 0.0))
            white = float(data["white_level"])
            knots = tuple(float(k) for k in data.get("knots") or ())
        except (KeyError, TypeError, ValueError) as exc:
            raise SveliveError(f"response data is missing or has a bad field: {exc}") from None
        if not coefficients or len(domain) != 2 or not domain[0] < domain[1]:
            raise SveliveError("response needs at least one coefficient and a domain [low, high] with low < high")
        if knots:
            if (len(knots) < 2 or len(coefficients) != len(knots) or not all(0 < k <= 1 for k in knots)
                    or any(b <= a for a, b in zip(knots, knots[1:]))):
                raise SveliveError(f"log-spline response needs 2 or more increasing knots in (0, 1] and one "
                                   f"coefficient per knot, got {len(knots)} knots and {len(coefficients)} "
                                   "coefficients")
        elif "degree" in data and int(data["degree"]) != len(coefficients) - 1:
            raise SveliveError(f"response degree {data['degree']} does not match its {len(coefficients)} coefficients")
        if not white > black:
            raise SveliveError(f"response white level {white:g} must be above its black level {black:g}")
        return cls(coefficients, domain, black, white, dict(data.get("stats", {})), knots)


def log_spline_basis(u: np.ndarray, knots: np.ndarray, derivative: bool = False) -> np.ndarray:
    """Restricted (natural) cubic spline basis in ``u`` without the constant, float64 (..., K - 1).

    Columns ``u`` and ``x_j(u)``, j = 1..K-2 (Harrell's form, scaled by the knot span squared):
    cubic between the knots, linear below the first and above the last, so a combination is
    a natural cubic spline. With ``derivative`` the columns' derivatives in ``u``.

    Args:
        u: float64 (...,) points, here log brightness.
        knots: float64 (K,) increasing, K >= 2.
    """
    u = np.asarray(u, np.float64)[..., None]
    t = np.asarray(knots, np.float64)
    last, second_last = t[-1], t[-2]
    if derivative:
        power = lambda x: 3.0 * np.maximum(x, 0.0) ** 2
        lead = np.ones_like(u)
    else:
        power = lambda x: np.maximum(x, 0.0) ** 3
        lead = u
    tj = t[:-2]
    gap = last - second_last
    x = (power(u - tj) - power(u - second_last) * (last - tj) / gap
         + power(u - last) * (second_last - tj) / gap) / (last - t[0]) ** 2
    return np.concatenate([lead, x], axis=-1)


def _log_spline_value(coef: np.ndarray, knots_u: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(f, df/dM) float64 of the log-spline with coefficients ``coef`` (constant first) at brightness ``m``;
    0 at m <= 0."""
    m = np.asarray(m, np.float64)
    positive = m > 0
    safe = np.where(positive, m, 1.0)
    u = np.log(safe)
    f = np.exp(coef[0] + log_spline_basis(u, knots_u) @ coef[1:])
    elasticity = log_spline_basis(u, knots_u, derivative=True) @ coef[1:]
    return np.where(positive, f, 0.0), np.where(positive, f * elasticity / safe, 0.0)


def linearise(raw: np.ndarray, response: Response, sensor: Sensor | None = None) -> np.ndarray:
    """A raw frame mapped through the inverse response back to linear DN, float32 (H, W).

    ``out = black + f(M) (white - black)`` with ``M = (raw - black) / (white - black)``:
    the same black and white level as the raw frame, so the result goes straight
    into :func:`svelive.reconstruct` (with the same levels); readings at or above
    white stay at white (saturated), linear values are clipped to [black, white].

    Args:
        raw: (H, W) raw frame, DN including black.
        response: the inverse response.
        sensor: black and white level; None takes the ones stored in the response.
    """
    raw = np.asarray(raw)
    if raw.ndim != 2:
        raise SveliveError(f"raw frame must be a single-channel 2-D array, got shape {raw.shape}")
    black = response.black_level if sensor is None else float(sensor.black_level)
    white = response.white_level if sensor is None else float(sensor.white_level)
    if raw.dtype.kind in "ui" and raw.dtype.itemsize <= 2:
        # one evaluation per possible code; the running maximum keeps the map monotone where a
        # polynomial wiggles slightly outside its measured range
        codes = np.arange(np.iinfo(raw.dtype).max + 1, dtype=np.float64)
        lut = np.maximum.accumulate(np.clip(response((codes - black) / (white - black)), 0.0, 1.0))
        lut = (black + lut * (white - black)).astype(np.float32)
        lut[codes >= white] = white
        return lut[raw]
    m = (raw.astype(np.float64) - black) / (white - black)
    out = black + np.clip(response(m), 0.0, 1.0) * (white - black)
    out[raw >= white] = white
    return out.astype(np.float32)
