"""Accuracy metrics for HDR reconstructions against ground truth.

All take float arrays of one shape, radiance in any linear unit (both in the
same unit). PU21 needs absolute luminance: both images are scaled together so
that the reference's 99.9th percentile maps to ``display_peak`` cd/m^2 (a
display-referred choice; dim and bright scenes are judged alike, by their
relative errors as a viewer would see them after exposure).

Colour images are float (H, W, 3) linear camera RGB. For the benchmark, camera
RGB is treated as linear sRGB (Rec. 709 primaries, D65 white, no white balance
and no camera matrix): luminance is its Rec. 709 luma, and the colour error is
CIEDE2000 between fixed sRGB renderings of truth and estimate (one exposure
from the truth, one tone curve, both shared; :func:`render_srgb`). The colour
error needs scikit-image (the optional extra ``bench``).
"""

from __future__ import annotations

import numpy as np

from svelive.core.errors import SveliveError
from svelive.exr import LUMA_WEIGHTS
from svelive.tonemap import srgb_encode

#: PU21 "banding_glare" parameters (Mantiuk and Azimi, PCS 2021).
PU21_BANDING_GLARE = (0.353487901, 0.3734658629, 8.277049286e-05, 0.9062562627,
                      0.09150303166, 0.9099517204, 596.3148142)
PU21_LUMINANCE_RANGE = (0.005, 10000.0)  # cd/m^2
PU21_PEAK = 256.0
DISPLAY_PEAK = 1000.0  # cd/m^2
MU_LAW = 5000.0
#: The fixed rendering for colour errors: the truth's log-average luminance goes to this mid grey.
RENDER_KEY = 0.18


def pu21_encode(luminance: np.ndarray) -> np.ndarray:
    """PU21 (banding_glare) perceptually uniform values of absolute luminance in cd/m^2."""
    p = PU21_BANDING_GLARE
    y = np.clip(np.asarray(luminance, np.float64), *PU21_LUMINANCE_RANGE) ** p[3]
    return np.maximum(p[6] * (((p[0] + p[1] * y) / (1 + p[2] * y)) ** p[4] - p[5]), 0)


def _psnr(a: np.ndarray, b: np.ndarray, peak: float) -> float:
    mse = float(np.mean((a - b) ** 2))
    return float("inf") if mse == 0 else float(10.0 * np.log10(peak * peak / mse))


def display_scale(reference: np.ndarray, display_peak: float = DISPLAY_PEAK) -> float:
    """Factor taking the reference's 99.9th percentile to ``display_peak`` cd/m^2."""
    return display_peak / max(float(np.percentile(reference, 99.9)), 1e-12)


def pu21_psnr(test: np.ndarray, reference: np.ndarray, display_peak: float = DISPLAY_PEAK,
              scale: float | None = None) -> float:
    """PSNR (dB) of PU21-encoded luminance, peak 256, both scaled by :func:`display_scale`.

    ``scale``: the factor to cd/m^2 when it is not the reference's own (a colour channel
    judged at its luminance's scale).
    """
    s = display_scale(reference, display_peak) if scale is None else scale
    return _psnr(pu21_encode(test * s), pu21_encode(reference * s), PU21_PEAK)


def log_psnr(test: np.ndarray, reference: np.ndarray) -> float:
    """PSNR (dB) of log2 radiance over the reference's range, values floored at 1e-4 of its 99.9th percentile."""
    floor = 1e-4 * float(np.percentile(reference, 99.9))
    lt = np.log2(np.maximum(test, floor))
    lr = np.log2(np.maximum(reference, floor))
    return _psnr(lt, lr, float(lr.max() - lr.min()) or 1.0)


def mu_law_psnr(test: np.ndarray, reference: np.ndarray, mu: float = MU_LAW) -> float:
    """PSNR (dB) after mu-law compression of both, normalised by the reference's maximum."""
    top = max(float(reference.max()), 1e-12)

    def compress(x: np.ndarray) -> np.ndarray:
        return np.log1p(mu * np.clip(x / top, 0, None)) / np.log1p(mu)

    return _psnr(compress(test), compress(reference), 1.0)


def error_stops_p99(test: np.ndarray, reference: np.ndarray) -> float:
    """99th percentile of |log2(test / reference)| over pixels above 1e-4 of the reference's 99.9th percentile."""
    floor = 1e-4 * float(np.percentile(reference, 99.9))
    mask = reference > floor
    return float(np.percentile(np.abs(np.log2(np.maximum(test[mask], floor) / reference[mask])), 99))


# ----- colour --------------------------------------------------------------------------------

def _rgb(image: np.ndarray, name: str) -> np.ndarray:
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3:
        raise SveliveError(f"{name} must be a colour image of shape (H, W, 3), got shape {image.shape}")
    return image


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Rec. 709 luma of linear camera RGB taken as linear sRGB, float32 (H, W) from (H, W, 3)."""
    return _rgb(rgb, "image").astype(np.float32) @ np.asarray(LUMA_WEIGHTS, np.float32)


def pu21_psnr_colour(test: np.ndarray, reference: np.ndarray,
                     display_peak: float = DISPLAY_PEAK) -> dict[str, float]:
    """PU21-PSNR (dB) of luminance and of each channel: {"Y", "R", "G", "B"}.

    Every channel is judged as a luminance at the scale that takes the
    reference's luminance 99.9th percentile to ``display_peak`` cd/m^2, so the
    channels keep their relative levels.
    """
    _rgb(test, "estimate")
    _rgb(reference, "reference")
    if test.shape != reference.shape:
        raise SveliveError(f"estimate {test.shape} and reference {reference.shape} differ in shape")
    ref_y = luminance(reference)
    s = display_scale(ref_y, display_peak)
    out = {"Y": pu21_psnr(luminance(test), ref_y, scale=s)}
    for c, name in enumerate("RGB"):
        out[name] = pu21_psnr(test[..., c], reference[..., c], scale=s)
    return out


def render_exposure(reference: np.ndarray, key: float = RENDER_KEY) -> float:
    """The fixed exposure of :func:`render_srgb`: the reference's log-average luminance maps to ``key``.

    Pixels below 1e-4 of the luminance's 99.9th percentile count at that floor (black must not
    drag the average to zero).
    """
    y = luminance(reference).astype(np.float64)
    floor = max(1e-4 * float(np.percentile(y, 99.9)), 1e-30)
    return key / float(np.exp(np.mean(np.log(np.maximum(y, floor)))))


def render_srgb(rgb: np.ndarray, exposure: float) -> np.ndarray:
    """The fixed rendering: ``rgb * exposure``, Reinhard's curve x / (1 + x) per channel, sRGB encoding.

    Returns float64 (H, W, 3) in [0, 1]. The curve is applied per channel, so bright
    saturated colours desaturate; truth and estimate are rendered alike.
    """
    x = np.maximum(_rgb(rgb, "image").astype(np.float64) * exposure, 0)
    return srgb_encode(x / (1.0 + x))


def skimage_color():
    """scikit-image's colour module; a one-line SveliveError naming the install when it is missing."""
    try:
        from skimage import color
    except ImportError:
        raise SveliveError("the colour error (CIEDE2000) needs scikit-image: pip install 'svelive[bench]'") from None
    return color


def srgb_to_lab(srgb: np.ndarray) -> np.ndarray:
    """CIELAB (D65, 2 degree observer) of sRGB-encoded values in [0, 1], float64 (..., 3) (scikit-image)."""
    return skimage_color().rgb2lab(srgb, illuminant="D65", observer="2")


def delta_e_2000(lab_test: np.ndarray, lab_reference: np.ndarray) -> np.ndarray:
    """CIEDE2000 colour difference (kL = kC = kH = 1) of two CIELAB arrays (..., 3), per pixel (scikit-image)."""
    return skimage_color().deltaE_ciede2000(lab_test, lab_reference)


def colour_error(test: np.ndarray, reference: np.ndarray, key: float = RENDER_KEY) -> dict[str, float]:
    """CIEDE2000 between the fixed sRGB renderings of estimate and truth: {"de2000_mean", "de2000_p99"}.

    Both are rendered with the exposure :func:`render_exposure` takes from the reference.
    """
    _rgb(test, "estimate")
    if test.shape != _rgb(reference, "reference").shape:
        raise SveliveError(f"estimate {test.shape} and reference {reference.shape} differ in shape")
    exposure = render_exposure(reference, key)
    de = delta_e_2000(srgb_to_lab(render_srgb(test, exposure)), srgb_to_lab(render_srgb(reference, exposure)))
    return {"de2000_mean": float(np.mean(de)), "de2000_p99": float(np.percentile(de, 99))}
