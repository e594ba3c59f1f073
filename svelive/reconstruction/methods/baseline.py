"""``baseline``: what a user could build from OpenCV alone, for the benchmark to compare against.

1. Split the frame into its sub-images, one per tile phase (a 2x2 tile gives
   four quarter-size images, each at one exposure).
2. Upsample each to full resolution with bilinear interpolation
   (cv2.warpAffine), placing every sample where the phase put it.
3. Merge per pixel with hat weights on the raw value, as in the classic
   exposure merges (Debevec and Malik): w(z) = 1 - |2 z / S - 1|, zero at or
   above the censor level, radiance = sum w z / e / sum w.
   Where every weight is zero the pixel is either saturated in every exposure
   (take the shortest exposure's value, a lower bound) or black in every one
   (take the longest exposure's value).

No noise model and no edge handling: that is what the project adds.
Uses the nominal tile; a calibrated per-pixel exposure map is ignored.
"""

from __future__ import annotations

import cv2
import numpy as np

from svelive.reconstruction.methods.base import Estimate, SveInput


def upsample_phase(sub: np.ndarray, phase: tuple[int, int], period: tuple[int, int],
                   shape: tuple[int, int]) -> np.ndarray:
    """Bilinear upsampling of one phase's sub-image, float32 (H, W).

    ``sub[j, i]`` was sampled at full-resolution pixel (py + th j, px + tw i);
    edges replicate the nearest sample.
    """
    (py, px), (th, tw) = phase, period
    h, w = shape
    # Inverse map: full-resolution (x, y) -> sub-image ((x - px) / tw, (y - py) / th).
    matrix = np.array([[1.0 / tw, 0.0, -px / tw], [0.0, 1.0 / th, -py / th]], np.float64)
    return cv2.warpAffine(sub, matrix, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_REPLICATE)


def run(inp: SveInput) -> Estimate:
    th, tw = inp.pattern.shape
    h, w = inp.shape
    full = np.float32(inp.sensor.range_dn)
    censor = np.float32(inp.sensor.censor_level)
    numerator = np.zeros((h, w), np.float32)
    denominator = np.zeros((h, w), np.float32)
    present: dict[float, np.ndarray] = {}  # the frame may be smaller than a tile: only the phases it holds
    for py in range(min(th, h)):
        for px in range(min(tw, w)):
            e = float(inp.pattern.tile[py, px])
            z = upsample_phase(np.ascontiguousarray(inp.signal[py::th, px::tw]), (py, px), (th, tw), (h, w))
            weight = 1.0 - np.abs(z * (2.0 / full) - 1.0)
            weight[z >= censor] = 0
            np.maximum(weight, 0, out=weight)
            radiance = z / np.float32(e)
            numerator += weight * radiance
            denominator += weight
            present.setdefault(e, radiance)
    e_min, e_max = min(present), max(present)
    shortest, longest = present[e_min], present[e_max]
    image = np.divide(numerator, denominator, out=np.zeros_like(numerator), where=denominator > 0)
    empty = denominator <= 0
    lower = empty & (shortest * np.float32(e_min) >= censor)
    np.copyto(image, shortest, where=lower)
    np.copyto(image, longest, where=empty & ~lower)
    np.maximum(image, 0, out=image)
    return Estimate(image, lower)
