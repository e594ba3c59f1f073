"""The public single-frame reconstruction: raw SVE frame in, HDR radiance out."""

from __future__ import annotations

import inspect

import numpy as np

from svelive.errors import SveliveError
from svelive.methods import DEFAULT_METHOD, METHODS
from svelive.methods.base import Estimate, SveInput, exposure_maps, smooth, support_size
from svelive.pattern import Pattern
from svelive.sensor import Sensor, container_bits


def methods() -> list[str]:
    """Names of the reconstruction methods, the default first."""
    return list(METHODS)


def sensor_for(raw: np.ndarray, black_level: float = 0, white_level: float | None = None,
               gain: float | None = None, read_noise: float | None = None) -> Sensor:
    """The Sensor a raw array implies: bit depth from its dtype unless the white level says more."""
    bits = container_bits(raw.dtype)
    if white_level is not None and white_level > 2**bits - 1:
        raise SveliveError(f"white level {white_level:g} exceeds the {raw.dtype} range")
    return Sensor(bits=bits, black_level=float(black_level), white_level=white_level, gain=gain,
                  read_noise=read_noise)


def prepare(raw: np.ndarray, pattern: Pattern | str, sensor: Sensor) -> SveInput:
    """Check a raw frame and turn it into the SveInput every method takes."""
    raw = np.asarray(raw)
    if raw.ndim != 2:
        raise SveliveError(f"raw frame must be a single-channel 2-D array, got shape {raw.shape}")
    if raw.size == 0:
        raise SveliveError("raw frame is empty")
    if raw.dtype.kind not in "uif":
        raise SveliveError(f"raw frame has unsupported dtype {raw.dtype}")
    if raw.dtype.kind == "f" and not np.all(np.isfinite(raw)):
        raise SveliveError("raw frame contains NaN or inf")
    pattern = Pattern.parse(pattern)
    exposure, _ = exposure_maps(pattern, raw.shape)
    signal = raw.astype(np.float32) - np.float32(sensor.black_level)
    censored = signal >= sensor.censor_level
    integral = raw.dtype.kind in "ui" and float(sensor.black_level).is_integer()
    return SveInput(signal=signal, exposure=exposure, censored=censored, pattern=pattern, sensor=sensor,
                    integral=integral)


def predicted_variance(image: np.ndarray, inp: SveInput) -> np.ndarray:
    """Noise variance (DN^2 at exposure 1, float32 (H, W)) the sensor model predicts for ``image``.

    For methods without a variance of their own: the inverse-variance
    combination of one tile's uncensored readings, i.e. the information
    e^2 / (e L / g + sigma^2) of every uncensored pixel at the estimate L,
    averaged over a window holding every phase of the tile, times the tile's size.
    """
    sensor = inp.sensor
    th, tw = inp.pattern.shape
    ones_y, ones_x = np.ones(support_size(th), np.float32), np.ones(support_size(tw), np.float32)
    per_pixel = inp.exposure * image
    per_pixel *= np.float32(1.0 / sensor.effective_gain)
    per_pixel += np.float32(sensor.floor_variance)
    np.divide(inp.exposure * inp.exposure, per_pixel, out=per_pixel)
    per_pixel[inp.censored] = 0
    per_tile = smooth(per_pixel, ones_y, ones_x)
    per_tile *= np.float32(th * tw / (ones_y.size * ones_x.size))
    return np.reciprocal(np.maximum(per_tile, np.float32(1e-30)))


def confidence_from_variance(image: np.ndarray, variance: np.ndarray, lower_bound: np.ndarray) -> np.ndarray:
    """Confidence in [0, 1], float32 (H, W): SNR / (1 + SNR) = L / (L + sigma), 0 where ``image`` is a lower bound."""
    sigma = np.sqrt(np.maximum(variance, 0)).astype(np.float32)
    sigma += image
    confidence = np.divide(image, sigma, out=np.zeros_like(sigma), where=sigma > 0)
    confidence[lower_bound] = 0
    return confidence


def confidence_map(estimate: Estimate, inp: SveInput) -> np.ndarray:
    """Confidence of a method's estimate (see :func:`confidence_from_variance`).

    Uses the method's own variance where it has one, else :func:`predicted_variance`.
    """
    return confidence_from_variance(estimate.image, estimate_variance(estimate, inp), estimate.lower_bound)


def estimate_variance(estimate: Estimate, inp: SveInput) -> np.ndarray:
    """The method's own variance of its estimate where it has one, else :func:`predicted_variance`."""
    return estimate.variance if estimate.variance is not None else predicted_variance(estimate.image, inp)


def reconstruct(raw: np.ndarray, pattern: Pattern | str, *, method: str | None = None, black_level: float = 0,
                white_level: float | None = None, gain: float | None = None, read_noise: float | None = None,
                return_confidence: bool = False, **options) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Reconstruct one HDR frame from one raw SVE frame.

    Args:
        raw: (H, W) uint8/uint16 raw DN (or float, already linearised), black level included.
        pattern: the exposure pattern or its text form, e.g. ``"1,4/16,64"``.
        method: one of :func:`methods`; None for the default.
        black_level, white_level: DN; the white level defaults to the dtype's maximum
            (pass it for 10/12-bit data in 16-bit containers).
        gain, read_noise: electrons per DN and read noise in DN, for the noise-aware
            weights; unknown values take the sensor defaults (sensor.py).
        return_confidence: also return the confidence map (see :func:`confidence_map`).
        **options: passed to the method (see its module).

    Returns:
        float32 (H, W) radiance in (raw - black) / e units, finite and >= 0;
        with ``return_confidence`` a tuple (image, confidence).
    """
    raw = np.asarray(raw)
    sensor = sensor_for(raw, black_level, white_level, gain, read_noise)
    inp = prepare(raw, pattern, sensor)
    estimate = run_method(inp, method, **options)
    if return_confidence:
        return estimate.image, confidence_map(estimate, inp)
    return estimate.image


def run_method(inp: SveInput, method: str | None = None, **options) -> Estimate:
    """Run a method by name on a prepared input, checking its options."""
    name = DEFAULT_METHOD if method is None else method
    if name not in METHODS:
        raise SveliveError(f"unknown method {name!r}; choose from {', '.join(METHODS)}")
    run = METHODS[name]
    accepted = set(inspect.signature(run).parameters) - {"inp"}
    unknown = set(options) - accepted
    if unknown:
        raise SveliveError(f"method {name!r} has no option {', '.join(sorted(unknown))}"
                           f" (it takes: {', '.join(sorted(accepted)) or 'none'})")
    estimate = run(inp, **options)
    image = estimate.image
    # Methods promise finite, non-negative float32 (the tests hold them to it); one cheap
    # reduction catches NaN and inf, which propagate into the sum, and repairs them.
    if image.dtype != np.float32 or not np.isfinite(image.sum()):
        image = np.nan_to_num(image.astype(np.float32), nan=0.0, posinf=np.finfo(np.float32).max, neginf=0.0)
        np.maximum(image, 0, out=image)
    return Estimate(image, estimate.lower_bound, estimate.variance)
