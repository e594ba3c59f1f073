"""``aggregate``: the paper's section 6.1, box aggregation and inversion of the effective response.

A tile-sized box holds every exposure of the tile once. For radiance that is
smooth over the box, the box mean of the clipped linear responses is
A(L) = mean_k min(e_k L, S): piecewise linear, rising with break points where
each exposure saturates (S = white - black). Inverting A gives radiance on the
lattice of box centres, which sits half a pixel off the pixel grid along each
even tile dimension; a two-tap average moves it back.

Uses the nominal tile: a calibrated per-pixel exposure map is ignored here.
"""

from __future__ import annotations

from concurrent.futures import Executor

from functools import lru_cache

import cv2
import numpy as np

from svelive.reconstruction.methods.base import Estimate, SveInput, in_strips, pad_same_phase, support_size


def effective_response(exposures: np.ndarray, full_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """Break points of A(L) = mean_k min(e_k L, S): (L, A) float64, ascending, from L = 0 to all saturated."""
    e = np.sort(np.asarray(exposures, dtype=np.float64).ravel())
    radiance = np.concatenate([[0.0], full_scale / np.unique(e)[::-1]])
    response = np.minimum(np.outer(radiance, e), full_scale).mean(axis=1)
    return radiance, response


def invert_response(response: np.ndarray, radiance_pts: np.ndarray, response_pts: np.ndarray) -> np.ndarray:
    """L = A^-1(response), float32, for the concave piecewise-linear A given by its break points.

    The inverse of a concave increasing function is convex, so it is the maximum
    of the lines through its segments: a few multiply-adds instead of a search.
    Responses at or beyond full saturation give the radiance where it begins.
    """
    slopes = np.diff(radiance_pts) / np.diff(response_pts)
    image = np.full(response.shape, radiance_pts[0], np.float32)
    line = np.empty_like(image)
    for slope, l0, a0 in zip(slopes, radiance_pts[:-1], response_pts[:-1]):
        np.multiply(response, np.float32(slope), out=line)
        line += np.float32(l0 - slope * a0)
        np.maximum(image, line, out=image)
    return np.minimum(image, np.float32(radiance_pts[-1]), out=image)


@lru_cache(maxsize=8)
def _lookup_table(tile_bytes: bytes, tile_shape: tuple[int, int], full_scale: float) -> np.ndarray:
    """Radiance for every integer box sum 0 .. n S of a tile of n pixels, float32."""
    tile = np.frombuffer(tile_bytes, np.float64).reshape(tile_shape)
    n = tile.size
    sums = np.arange(int(round(n * full_scale)) + 1, dtype=np.float32)
    table = invert_response(sums / np.float32(n), *effective_response(tile, full_scale))
    table.setflags(write=False)
    return table


def run(inp: SveInput, *, workers: int | Executor = 1) -> Estimate:
    """``workers``: a thread count or an Executor for the frame's strips (base.map_on); the result does not depend on it."""
    return in_strips(_run, inp, halo=inp.pattern.shape[0] + 1, workers=workers)


def _run(inp: SveInput) -> Estimate:
    th, tw = inp.pattern.shape
    h, w = inp.shape
    full_scale = inp.sensor.range_dn
    # Not clipped at 0: negative readings (noise below black) keep the box mean unbiased;
    # the inversion maps any mean below 0 to 0 and any above full scale to saturation.
    signal = inp.signal
    if h < th or w < tw:  # no whole tile to aggregate: each pixel on its own
        own = np.clip(signal, 0.0, full_scale) / inp.exposure
        return Estimate(own.astype(np.float32), inp.censored.copy())

    # Box of the tile's size whose centre lies +0.5 px (along even dimensions) from the anchor pixel.
    ay, ax = (th - 1) // 2, (tw - 1) // 2
    padded = pad_same_phase(signal, (th, tw), (ay, ax), (th - 1 - ay, tw - 1 - ax))
    box_sum = cv2.boxFilter(padded, cv2.CV_32F, (tw, th), anchor=(0, 0), normalize=False,
                            borderType=cv2.BORDER_CONSTANT)[:h, :w]
    if inp.integral and float(full_scale).is_integer():
        # Integer readings: the box sum is an exact integer, so the inversion is a table look-up.
        table = _lookup_table(inp.pattern.tile.tobytes(), inp.pattern.shape, full_scale)
        image = np.take(table, box_sum.astype(np.int32), mode="clip")  # clip: no bounds check, sums are in range
    else:
        image = invert_response(box_sum / np.float32(th * tw), *effective_response(inp.pattern.tile, full_scale))

    # Back to the pixel grid: average each box centre with its neighbour above / to the left.
    kernel_y = np.array([0.5, 0.5] if th % 2 == 0 else [1.0], np.float32)
    kernel_x = np.array([0.5, 0.5] if tw % 2 == 0 else [1.0], np.float32)
    image = cv2.sepFilter2D(image, cv2.CV_32F, kernel_x, kernel_y,
                            anchor=(len(kernel_x) - 1, len(kernel_y) - 1), borderType=cv2.BORDER_REPLICATE)
    # Where every pixel of the window is saturated the inversion already returned the
    # radiance at which the lowest exposure saturates: the lower bound the frame implies.
    window = (support_size(th), support_size(tw))
    if inp.censored.any():
        all_censored = cv2.erode(inp.censored.view(np.uint8), np.ones(window, np.uint8),
                                 borderType=cv2.BORDER_REFLECT_101).view(bool)
    else:
        all_censored = np.zeros(inp.shape, bool)
    return Estimate(image, all_censored)
