"""The per-channel split baseline (svelive.reconstruction.colour, mode ``"split"``): the mono method per
CFA-phase sub-image, then demosaicing in a log encoding (OpenCV's edge-aware Bayer conversion, or a tent
normalised convolution), with the luminance's variance and lower bounds carried along (:func:`split`)."""

from __future__ import annotations

import cv2
import numpy as np

from svelive.core.camera import colour_phase
from svelive.core.cfa import ColourFilter
from svelive.reconstruction.colour.cells import cell_layout
from svelive.reconstruction.methods import MethodSpec
from svelive.reconstruction.methods.base import Estimate, SveInput, exposure_maps, smooth


def split(inp: SveInput, spec: MethodSpec, **options) -> Estimate:
    """The baseline (package docstring): the mono method per CFA-phase sub-image, then demosaicing."""
    cfa, pattern = inp.cfa, inp.pattern
    reduced = cfa.block_tile()
    mosaic, variance = np.empty(inp.shape, np.float32), np.empty(inp.shape, np.float32)
    lower = np.empty(inp.shape, bool)
    for qy in range(reduced.shape[0]):
        for qx in range(reduced.shape[1]):
            rows, cols, sub_pattern = colour_phase(pattern, cfa, inp.shape, (qy, qx))
            if rows.size == 0 or cols.size == 0:
                continue
            where = np.ix_(rows, cols)
            sub = SveInput(np.ascontiguousarray(inp.signal[where]), exposure_maps(sub_pattern, (rows.size, cols.size))[0],
                           np.ascontiguousarray(inp.censored[where]), sub_pattern, inp.sensor, inp.integral)
            est = spec.run(sub, **options)
            mosaic[where] = est.image
            lower[where] = est.lower_bound
            variance[where] = np.inf if est.variance is None else est.variance
    floor = float(np.sqrt(inp.sensor.floor_variance) / pattern.tile.max())  # noise floor of the longest exposure
    image = demosaic(mosaic, cfa, floor)
    share = cell_layout(pattern, cfa).share
    luminance = np.ascontiguousarray(image @ share)
    has_variance = bool(np.all(np.isfinite(variance[:1])))
    lum_variance = _interpolated_variance(variance, cfa, share) if has_variance else None
    lum_lower = _spread(lower, cfa)
    return Estimate(image, lum_lower, lum_variance, luminance)


def demosaic(mosaic: np.ndarray, cfa: ColourFilter, floor: float) -> np.ndarray:
    """RGB (H, W, 3) float32 from an HDR mosaic (H, W) (>= 0, DN), interpolated in log2(x + floor)
    encoded to 16 bits: OpenCV's edge-aware Bayer demosaicing, or a tent normalised convolution."""
    log = np.log2(np.maximum(mosaic, 0) + np.float32(floor))
    low, high = float(log.min()), float(log.max())
    step = max(high - low, 1e-6) / 65535.0
    if cfa.is_bayer() and min(mosaic.shape) >= 2:
        code = np.rint((log - low) / step).astype(np.uint16)
        rgb_code = cv2.demosaicing(code, getattr(cv2, f"COLOR_Bayer{cfa.name}2RGB_EA")).astype(np.float32)
    else:
        rgb_code = np.stack([_tent_interpolation(np.rint((log - low) / step).astype(np.float32), cfa, c)
                             for c in range(3)], axis=-1)
    rgb = np.exp2(rgb_code * np.float32(step) + np.float32(low)) - np.float32(floor)
    return np.maximum(rgb, 0, out=rgb).astype(np.float32, copy=False)


def _tent(length: int) -> np.ndarray:
    """Separable tent reaching ``length`` - 1 pixels each side, float32 (2 length - 1,)."""
    return np.concatenate([np.arange(1, length + 1), np.arange(length - 1, 0, -1)]).astype(np.float32)


def _tent_interpolation(values: np.ndarray, cfa: ColourFilter, channel: int) -> np.ndarray:
    """Channel ``channel`` of a mosaic at every pixel: its own value where the CFA has it, else
    the tent-weighted mean of its samples around (normalised convolution), float32 (H, W)."""
    mask = (cfa.channel_map(values.shape) == channel).astype(np.float32)
    ky, kx = _tent(cfa.shape[0]), _tent(cfa.shape[1])
    num, den = smooth(values * mask, ky, kx), smooth(mask, ky, kx)
    out = np.divide(num, den, out=np.zeros_like(num), where=den > 0)
    np.copyto(out, values, where=mask > 0)
    return out


def _interpolated_variance(variance: np.ndarray, cfa: ColourFilter, share: np.ndarray) -> np.ndarray:
    """Variance of the luminance sum_c n_c C_c, each channel's variance interpolated as its values."""
    out = np.zeros(variance.shape, np.float32)
    for c in range(3):
        out += np.float32(share[c] ** 2) * _tent_interpolation(variance, cfa, c)
    return out


def _spread(lower: np.ndarray, cfa: ColourFilter) -> np.ndarray:
    """Pixels whose interpolation reads a lower bound: ``lower`` dilated over the CFA's period."""
    if not lower.any():
        return lower
    size = (2 * cfa.shape[1] - 1, 2 * cfa.shape[0] - 1)
    return cv2.dilate(lower.view(np.uint8), np.ones(size[::-1], np.uint8)).view(bool)
