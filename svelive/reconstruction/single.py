"""The public single-frame reconstruction: raw SVE frame in, HDR radiance out."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from svelive.core.camera import Camera, camera_for_raw
from svelive.core.cfa import ColourFilter
from svelive.core.errors import SveliveError
from svelive.core.pattern import Pattern
from svelive.noise import NoiseEstimate
from svelive.reconstruction.input import prepare, with_noise_model
from svelive.reconstruction.methods import DEFAULT_METHOD, METHODS, MethodSpec
from svelive.reconstruction.methods.base import Estimate, SveInput, smooth, support_size


def methods() -> list[str]:
    """Names of the reconstruction methods, the default first."""
    return list(METHODS)


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
    return confidence_from_variance(estimate.plane, estimate_variance(estimate, inp), estimate.lower_bound)


def estimate_variance(estimate: Estimate, inp: SveInput) -> np.ndarray:
    """The method's own variance of its estimate where it has one, else :func:`predicted_variance`."""
    return estimate.variance if estimate.variance is not None else predicted_variance(estimate.plane, inp)


def reconstruct(raw: np.ndarray, pattern: Pattern | str | Camera, *, cfa: ColourFilter | str | None = None,
                method: str | None = None, black_level: float = 0, white_level: float | None = None,
                gain: float | None = None, read_noise: float | None = None, colour: str = "joint",
                noise: NoiseEstimate | str = "estimate", return_confidence: bool = False,
                **options) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Reconstruct one HDR frame from one raw SVE frame.

    Args:
        raw: (H, W) uint8/uint16 raw DN (or float, already linearised), black level included.
        pattern: the exposure pattern or its text form, e.g. ``"1,4/16,64"``, or a colour
            layout name (svelive.core.camera.COLOUR_LAYOUTS); or a whole svelive.Camera, which
            then stands for ``cfa`` and the sensor levels too.
        cfa: the colour filter layout (``"RGGB"``, ``"R,G/G,B"``, svelive.core.cfa.PRESETS), or
            None for a monochrome sensor.
        method: one of :func:`methods`; None for the default.
        black_level, white_level: DN; the white level defaults to the dtype's maximum
            (pass it for 10/12-bit data in 16-bit containers).
        gain, read_noise: electrons per DN and read noise in DN, for the noise-aware
            weights; unknown values are estimated from the frame (svelive.noise), see ``noise``.
        colour: with a CFA, ``"joint"`` (the method reconstructs luminance from every
            pixel and colour from the local channel ratios) or ``"split"`` (the method
            on each CFA channel alone, then demosaicing: the baseline).
        noise: where the sensor lacks gain or read noise: ``"estimate"`` (from this frame,
            :func:`svelive.noise.estimate_from_frame`), ``"default"`` (the fixed defaults of sensor.py),
            or a :class:`svelive.noise.NoiseEstimate` already made (e.g. to print it too).
            Given values are never overridden.
        return_confidence: also return the confidence map (see :func:`confidence_map`).
        **options: passed to the method (see its module).

    Returns:
        float32 radiance in (raw - black) / e units, finite and >= 0: (H, W), or
        (H, W, 3) linear camera RGB (before white balance) with a CFA; with
        ``return_confidence`` a tuple (image, confidence (H, W)).
    """
    if isinstance(pattern, Camera):
        if cfa is not None:
            raise SveliveError("give the colour filter inside the Camera, not beside it")
        camera = pattern
    else:
        camera = camera_for_raw(raw, pattern, cfa=cfa, black_level=black_level, white_level=white_level,
                                gain=gain, read_noise=read_noise)
    inp = prepare(raw, camera)
    if isinstance(noise, NoiseEstimate) or noise == "estimate":
        camera, inp, _ = with_noise_model(raw, camera, inp, noise if isinstance(noise, NoiseEstimate) else None)
    elif noise != "default":
        raise SveliveError(f"noise must be 'estimate', 'default' or a NoiseEstimate, got {noise!r}")
    estimate = run_method(inp, method, colour=colour, variance=return_confidence, **options)
    if return_confidence:
        return estimate.image, confidence_map(estimate, inp)
    return estimate.image


def method_spec(method: str | None) -> MethodSpec:
    """The registered method of this name (None: the default); a one-line error listing the names otherwise."""
    name = DEFAULT_METHOD if method is None else method
    if name not in METHODS:
        raise SveliveError(f"unknown method {name!r}; choose from {', '.join(METHODS)}")
    return METHODS[name]


def run_method(inp: SveInput, method: str | None = None, *, colour: str = "joint", variance: bool = True,
               **options) -> Estimate:
    """Run a method by name on a prepared input, checking its options; colour inputs go through
    svelive.reconstruction.colour (``colour``: ``"joint"`` or ``"split"``; ``variance`` False for a caller that
    reads only the image: the joint estimate's refined variance is then not written, and None)."""
    spec = method_spec(method)
    spec.check_options(options)
    checked = False
    if inp.cfa is not None:
        from svelive.reconstruction.colour import run_colour

        estimate, checked = run_colour(inp, spec, colour, variance=variance, **options)
    else:
        estimate = spec.run(inp, **options)
    image = estimate.image
    # Methods promise finite, non-negative float32 (the tests hold them to it); one cheap
    # reduction catches NaN and inf, which propagate into the sum, and repairs them. The joint
    # colour's passes check each value as they write it, while in cache (``checked``: every one finite).
    if image.dtype != np.float32 or not (checked or np.isfinite(image.sum())):
        image = np.nan_to_num(image.astype(np.float32), nan=0.0, posinf=np.finfo(np.float32).max, neginf=0.0)
        np.maximum(image, 0, out=image)
    return replace(estimate, image=image)
