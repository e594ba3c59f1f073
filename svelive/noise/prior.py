"""The prior every estimate is combined with, and the NoiseEstimate of a fitted line (given values kept, estimated
ones combined with the prior, the sensor defaults where the data told nothing). A value the frame does not tell
carries the prior's uncertainty."""

from __future__ import annotations

import math

from svelive.core.sensor import DEFAULT_FULL_WELL_E, DEFAULT_READ_NOISE_E, Sensor
from svelive.noise.model import QUANTISATION_VARIANCE, LineFit, NoiseEstimate


#: The prior every estimate is combined with: log-normal around the sensor defaults (sensor.py), one
#: standard deviation a factor of 4 (full wells of 2 500-40 000 e- for 12 bits are within one sigma).
PRIOR_LOG_SIGMA = math.log(4.0)


def _prior_sigma(default: float) -> float:
    """The standard uncertainty of a value the data did not tell (the prior's alone): its log-sigma times
    the value, so that ``2 sigma`` spans the factor the prior allows (about 16 either way)."""
    return PRIOR_LOG_SIGMA * default


def _with_prior(value: float, sigma: float, default: float) -> tuple[float, float]:
    """Combine an estimate and its standard uncertainty with the log-normal prior around ``default``.

    A well-measured value barely moves (at 15 % uncertainty the prior weighs about 1 %); a value the
    data hardly constrains falls back towards the default instead of swinging wide.
    """
    s_est = sigma / max(value, 1e-12)
    if not math.isfinite(s_est) or s_est <= 0:
        return value, sigma
    w_est, w_prior = 1.0 / s_est**2, 1.0 / PRIOR_LOG_SIGMA**2
    log_v = (w_est * math.log(max(value, 1e-12)) + w_prior * math.log(default)) / (w_est + w_prior)
    post = math.exp(log_v)
    return post, post / math.sqrt(w_est + w_prior)


def _gain_log_sigma(fit: LineFit) -> float:
    """The gain's uncertainty as a log-sigma: ``-ln(1 - sigma / slope)``, the gain's rise where the slope
    is one standard deviation lower (the side on which ``1 / slope`` grows without bound). For a
    well-measured slope this is ``sigma / slope``; for a slope hardly above its noise it is large,
    where ``sigma / slope`` would state an overestimated slope's gain to within a factor of 2."""
    rel = math.sqrt(max(fit.cov[0, 0], 0.0)) / fit.slope
    return -math.log(max(1.0 - rel, 1e-6))


def estimate_from_fit(fit: LineFit | None, sensor: Sensor, samples: int) -> NoiseEstimate:
    """The NoiseEstimate of a fitted line: the sensor's given values kept, each estimated value combined
    with the prior (:func:`_with_prior`), the defaults where the fit failed (source "default")."""
    given_gain, given_read = sensor.gain, sensor.read_noise
    if given_gain is not None and given_read is not None:
        return NoiseEstimate(given_gain, given_read, 0.0, 0.0, samples, "given")
    default_gain = given_gain if given_gain is not None else DEFAULT_FULL_WELL_E / sensor.range_dn
    default_read = DEFAULT_READ_NOISE_E / default_gain
    if fit is None:
        read = given_read if given_read is not None else default_read
        return NoiseEstimate(default_gain, read, 0.0 if given_gain is not None else _prior_sigma(default_gain),
                             0.0 if given_read is not None else _prior_sigma(read), samples, "default")
    if given_gain is not None:
        gain, gain_sigma = given_gain, 0.0
    elif fit.fixed_slope:  # the data told only the read noise; the gain stays the default, as uncertain as the prior
        gain, gain_sigma = default_gain, _prior_sigma(default_gain)
    else:
        gain = 1.0 / fit.slope
        gain, gain_sigma = _with_prior(gain, gain * _gain_log_sigma(fit), default_gain)
    if given_read is not None:
        read, read_sigma = given_read, 0.0
    else:
        read = math.sqrt(max(fit.intercept - QUANTISATION_VARIANCE, 0.0))
        sd_r = math.sqrt(max(fit.cov[1, 1], 0.0))
        # below about one standard error of the variance the read noise is known only to be small
        read_sigma = sd_r / (2 * read) if read > math.sqrt(sd_r) else math.sqrt(sd_r)
        read, read_sigma = _with_prior(max(read, 0.05), read_sigma, DEFAULT_READ_NOISE_E / default_gain)
    return NoiseEstimate(gain, read, gain_sigma, read_sigma, samples, "estimated")
