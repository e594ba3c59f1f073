"""Per-pixel helpers both motion tests share: the noise-model disagreement test, mask growth, strips."""

from __future__ import annotations

import cv2
import numpy as np

from svelive.jit import flat, kernel


def _grow(mask: np.ndarray, window: tuple[int, int]) -> np.ndarray:
    """Dilate a bool (H, W) mask by a centred (rows, cols) window."""
    return cv2.dilate(mask.view(np.uint8), np.ones(window, np.uint8), borderType=cv2.BORDER_REPLICATE).view(bool)


#: The 8 neighbours of a pixel, as a dilation kernel.
_RING = np.array([[1, 1, 1], [1, 0, 1], [1, 1, 1]], np.uint8)


def _confirmed(flagged: np.ndarray) -> np.ndarray:
    """bool (H, W): flagged pixels with at least one flagged 8-neighbour (none beyond the border)."""
    mask = flagged.view(np.uint8)
    return cv2.bitwise_and(mask, cv2.dilate(mask, _RING)).view(bool)


def _widen(mask: np.ndarray, pixels: int) -> np.ndarray:
    """Dilate a bool (H, W) mask by a (2 pixels + 1)^2 square."""
    if pixels <= 0:
        return mask
    square = np.ones((2 * pixels + 1, 2 * pixels + 1), np.uint8)
    return cv2.dilate(mask.view(np.uint8), square, borderType=cv2.BORDER_REPLICATE).view(bool)


def disagree(a: np.ndarray, var_a: np.ndarray, b: np.ndarray, var_b: np.ndarray, sigmas: float) -> np.ndarray:
    """bool: ``(a - b)^2 > sigmas^2 (var_a + var_b)``, the noise-model test of two float32 estimates (broadcast)."""
    arrays = [np.ascontiguousarray(x, np.float32) for x in np.broadcast_arrays(a, var_a, b, var_b)]
    out = np.empty(arrays[0].shape, bool)
    _disagree_pass(*flat(*arrays, out), np.float32(sigmas * sigmas))
    return out


@kernel
def _disagrees(a, var_a, b, var_b, k2):
    """:func:`disagree` of one pixel, k2 = sigmas^2 (float32)."""
    diff = a - b
    return diff * diff > (var_a + var_b) * k2


@kernel
def _disagree_pass(a, var_a, b, var_b, out, k2):
    for k in range(a.size):
        out[k] = _disagrees(a[k], var_a[k], b[k], var_b[k], k2)


#: Rows per strip of the per-pixel passes: small enough for a strip's arrays to stay in cache
#: from its test to its update.
STRIP_ROWS = 64


def _strips(height: int, rows: int) -> list[slice]:
    """The frame's rows in strips of ``rows`` (the last one shorter)."""
    rows = max(1, int(rows))
    return [slice(top, min(top + rows, height)) for top in range(0, height, rows)]


@kernel
def _maximum(a, b):
    """max(a, b) with numpy's NaN propagation from ``a``."""
    return b if a < b else a
