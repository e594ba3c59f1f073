"""``cubic``: the paper's section 6.2, off-grid unknowns solved through cubic convolution.

1. Discard censored (saturated) and too-dark readings: those whose expected
   signal, predicted from their 3x3 neighbourhood, is below ``dark_level`` DN
   (by default twice the read noise). Judging the prediction, not the reading,
   avoids selecting readings by their own noise (an upward bias in the dark).
2. Normalise the rest by exposure: x = s / e.
3. The unknowns are off-grid values O at the centre of every 2x2 pixel group.
   On-grid values follow from the off-grid ones by cubic convolution (eq. 5),
   Keys' kernel with a = -0.5: taps -1/16, 9/16, 9/16, -1/16 at +-0.5, +-1.5.
4. Around one off-grid point its 4x4 on-grid neighbours depend on 7x7 off-grid
   values: M = F O with F 16x49 (eq. 6). Keeping the N undiscarded rows,
   O = pinv(F~) M~ (eq. 8), and the centre unknown is kept.
5. Eq. 5 resamples the off-grid values to the pixel grid.

The minimum-norm caution. Eq. 8 is the minimum-norm solution of an
under-determined system, and the minimum-norm O is not the flat one: with all
16 readings of a flat field equal to 20, the centre comes back at ~13 (the
coefficients a of the centre row of pinv(F~) sum to ~0.65, not 1). We keep the
paper's solve and normalise those coefficients, a / sum(a), so a flat field is
reproduced exactly whatever is discarded; ``literal=True`` gives the unnormalised
form for comparison. Where fewer readings remain the solve leans on fewer
neighbours and can ring near discarded regions; negative results are clipped to 0.

Speed: F and the solve depend only on which of the 16 readings are kept (a
16-bit code), not on the image, so the centre row is computed once per code
and cached; a frame costs one 4x4 correlation plus a gather where readings were
discarded.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from svelive.reconstruction.methods.base import Estimate, SveInput, smooth

FULL = (1 << 16) - 1


def keys_kernel(distance: np.ndarray | float, a: float = -0.5) -> np.ndarray:
    """Keys' cubic convolution kernel f(d) (the paper's cubic interpolation kernel)."""
    d = np.abs(np.asarray(distance, dtype=np.float64))
    near = ((a + 2) * d - (a + 3)) * d * d + 1
    far = ((a * d - 5 * a) * d + 8 * a) * d - 4 * a
    return np.where(d <= 1, near, np.where(d < 2, far, 0.0))


def forward_matrix() -> np.ndarray:
    """F (16x49): the 4x4 on-grid readings around an off-grid point from its 7x7 off-grid neighbours (eq. 6).

    Row k = 4 dy + dx for on-grid offsets dy, dx in -1..2 from the point's top-left
    pixel; column u = 7 (oy + 3) + (ox + 3) for off-grid offsets oy, ox in -3..3.
    """
    on = np.arange(-1, 3)
    off = np.arange(-3, 4)
    fy = keys_kernel(0.5 + off[None, :] - on[:, None])  # (4, 7)
    return np.einsum("ab,cd->acbd", fy, fy).reshape(16, 49)


@lru_cache(maxsize=None)
def centre_coefficients(code: int, literal: bool = False) -> np.ndarray:
    """Weights (16,) of the kept readings for the centre off-grid value, for the keep-mask ``code``."""
    keep = np.array([(code >> k) & 1 for k in range(16)], dtype=bool)
    coefficients = np.zeros(16, np.float64)
    if not keep.any():
        return coefficients.astype(np.float32)
    row = np.linalg.pinv(forward_matrix()[keep])[24]
    total = row.sum()
    if not literal:
        # Normalised so that a flat field comes back flat; a degenerate sum falls back to the mean.
        row = row / total if abs(total) > 1e-3 else np.full(row.shape, 1.0 / row.size)
    coefficients[keep] = row
    return coefficients.astype(np.float32)


def local_radiance(inp: SveInput) -> np.ndarray:
    """Shot-noise estimate sum(s) / sum(e) of the other uncensored readings in 3x3, float32 (H, W).

    Deciding "too dark" from this prediction, which leaves the reading itself
    out, keeps the discard from selecting readings by their own noise (that
    would bias dark regions upwards).
    """
    valid = (~inp.censored).astype(np.float32)
    box = np.ones(3, np.float32)
    signal = smooth(inp.signal * valid, box, box) - inp.signal * valid
    exposure = smooth(inp.exposure * valid, box, box) - inp.exposure * valid
    return signal / np.maximum(exposure, 1e-30)


def run(inp: SveInput, *, dark_level: float | None = None, literal: bool = False) -> Estimate:
    h, w = inp.shape
    if dark_level is None:
        dark_level = 2.0 * inp.sensor.effective_read_noise
    pad = 3
    measured = ~inp.censored
    radiance = np.pad(inp.signal / inp.exposure, pad, mode="symmetric").astype(np.float32)
    keep_measured = np.pad(measured, pad, mode="symmetric")
    keep = np.pad(measured & (inp.exposure * local_radiance(inp) >= dark_level), pad, mode="symmetric")
    oh, ow = h + 3, w + 3  # off-grid lattice: point (a, b) has on-grid neighbours padded[a:a+4, b:b+4]

    def codes(mask: np.ndarray) -> np.ndarray:
        code = np.zeros((oh, ow), np.int64)
        for k in range(16):
            dy, dx = divmod(k, 4)
            code |= mask[dy:dy + oh, dx:dx + ow].astype(np.int64) << k
        return code

    code = codes(keep)
    # Where the dark threshold discarded every reading, use the dark ones rather than nothing.
    code = np.where(code == 0, codes(keep_measured), code)

    full = centre_coefficients(FULL, literal).reshape(4, 4)
    offgrid = cv2.filter2D(radiance, cv2.CV_32F, full, anchor=(0, 0), borderType=cv2.BORDER_CONSTANT)[:oh, :ow]
    partial = np.nonzero(code != FULL)
    if partial[0].size:
        part_codes = code[partial]
        unique, inverse = np.unique(part_codes, return_inverse=True)
        table = np.stack([centre_coefficients(int(c), literal) for c in unique])
        values = np.zeros(part_codes.size, np.float32)
        for k in range(16):
            dy, dx = divmod(k, 4)
            values += table[inverse, k] * radiance[partial[0] + dy, partial[1] + dx]
        offgrid[partial] = values

    lower = code == 0
    if lower.any():  # every reading censored: the largest bound they imply
        bound = np.pad(np.where(inp.censored, inp.signal / inp.exposure, 0).astype(np.float32), pad, mode="symmetric")
        bound = cv2.dilate(bound, np.ones((4, 4), np.uint8), anchor=(0, 0), borderType=cv2.BORDER_CONSTANT,
                           borderValue=0)[:oh, :ow]
        offgrid[lower] = bound[lower]

    taps = keys_kernel(np.array([1.5, 0.5, 0.5, 1.5])).astype(np.float32)
    image = cv2.sepFilter2D(offgrid, cv2.CV_32F, taps, taps, anchor=(0, 0), borderType=cv2.BORDER_CONSTANT)[:h, :w]
    lower_bound = cv2.erode(lower.view(np.uint8), np.ones((2, 2), np.uint8), anchor=(0, 0),
                            borderType=cv2.BORDER_REPLICATE)[1:h + 1, 1:w + 1].astype(bool)
    image = np.maximum(image, 0)
    if lower_bound.any():
        image = np.where(lower_bound, np.maximum(image, offgrid[1:h + 1, 1:w + 1]), image)
    return Estimate(image.astype(np.float32, copy=False), lower_bound)
