"""Accuracy metrics for HDR reconstructions against ground truth.

All take float arrays of one shape, radiance in any linear unit (both in the
same unit). PU21 needs absolute luminance: both images are scaled together so
that the reference's 99.9th percentile maps to ``display_peak`` cd/m^2 (a
display-referred choice; dim and bright scenes are judged alike, by their
relative errors as a viewer would see them after exposure).
"""

from __future__ import annotations

import numpy as np

#: PU21 "banding_glare" parameters (Mantiuk and Azimi, PCS 2021).
PU21_BANDING_GLARE = (0.353487901, 0.3734658629, 8.277049286e-05, 0.9062562627,
                      0.09150303166, 0.9099517204, 596.3148142)
PU21_LUMINANCE_RANGE = (0.005, 10000.0)  # cd/m^2
PU21_PEAK = 256.0
DISPLAY_PEAK = 1000.0  # cd/m^2
MU_LAW = 5000.0


def pu21_encode(luminance: np.ndarray) -> np.ndarray:
    """PU21 (banding_glare) perceptually uniform values of absolute luminance in cd/m^2."""
    p = PU21_BANDING_GLARE
    y = np.clip(np.asarray(luminance, np.float64), *PU21_LUMINANCE_RANGE) ** p[3]
    return np.maximum(p[6] * (((p[0] + p[1] * y) / (1 + p[2] * y)) ** p[4] - p[5]), 0)


def _psnr(a: np.ndarray, b: np.ndarray, peak: float) -> float:
    mse = float(np.mean((a - b) ** 2))
    return float("inf") if mse == 0 else 10.0 * np.log10(peak * peak / mse)


def display_scale(reference: np.ndarray, display_peak: float = DISPLAY_PEAK) -> float:
    """Factor taking the reference's 99.9th percentile to ``display_peak`` cd/m^2."""
    return display_peak / max(float(np.percentile(reference, 99.9)), 1e-12)


def pu21_psnr(test: np.ndarray, reference: np.ndarray, display_peak: float = DISPLAY_PEAK) -> float:
    """PSNR (dB) of PU21-encoded luminance, peak 256, both scaled by :func:`display_scale`."""
    s = display_scale(reference, display_peak)
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
