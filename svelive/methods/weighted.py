"""``weighted``: noise-optimal combination of every exposure's local interpolation (the default).

For each exposure level k, the uncensored pixels of that level give unbiased
radiance estimates x = s / e, and a binomial window that holds every phase of
the tile (3x3 for a 2x2 tile) interpolates them at every pixel:
m_k = sum_i G_i x_i / sum_i G_i over level-k pixels i. The levels are then
merged with inverse-variance weights of the Poisson-Gaussian model (sensor.py)
evaluated at the pixel's own predicted radiance L0:

    w_k = n_k e_k^2 / (e_k L0 / g + sigma^2),   L = sum_k w_k m_k / sum_k w_k

with n_k the level's share of the window. Two rules keep it unbiased:
- a level whose window holds any censored (saturated) pixel is left out at
  that pixel: its surviving pixels are the darker ones, so averaging them
  would bias the estimate low next to highlights;
- the weights of all pixels of one level are equal within the window, so a
  darker neighbour never counts for more than a brighter one.
L0 is the shot-noise maximum-likelihood estimate over the same window,
sum(s) / sum(e) over uncensored pixels. Where every level has a censored pixel
in the window, L0 itself is the result (it still uses every uncensored pixel),
raised to a censored pixel's own bound where it is lower;
where the window holds nothing uncensored, the result is the lower bound the
censored pixels imply. Nothing is tuned to an image: weights come from the
noise model, exclusions from the censoring alone.
"""

from __future__ import annotations

from concurrent.futures import Executor

from functools import lru_cache

import cv2
import numpy as np

from svelive.methods.base import (Estimate, SveInput, at_least, binomial_kernel, censored_lower_bound, in_strips,
                                  smooth, support_size)
from svelive.pattern import Pattern


@lru_cache(maxsize=16)
def _level_layout(pattern: Pattern, shape: tuple[int, int]) -> list[tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """Per exposure level: (exposure, mask bool, mask float32, window share n_k, effective sample count), cached."""
    th, tw = pattern.shape
    ky, kx = binomial_kernel(support_size(th)), binomial_kernel(support_size(tw))
    index = pattern.level_index_map(shape)
    layout = []
    for k, exposure in enumerate(pattern.levels):
        is_level = index == k
        mask = is_level.astype(np.float32)
        share = smooth(mask, ky, kx)
        squares = smooth(mask, ky * ky, kx * kx)
        effective = share * share / np.maximum(squares, 1e-12)
        for array in (is_level, mask, share, effective):
            array.setflags(write=False)
        layout.append((float(exposure), is_level, mask, share, effective))
    return layout


def run(inp: SveInput, *, return_variance: bool = False, workers: int | Executor = 1) -> Estimate:
    """``workers``: a thread count or an Executor for the frame's strips (base.map_on); the result does not depend on it."""
    halo = max(support_size(s) for s in inp.pattern.shape)
    return in_strips(_run, inp, halo, rows=96, workers=workers, return_variance=return_variance)


def _run(inp: SveInput, *, return_variance: bool = False) -> Estimate:
    th, tw = inp.pattern.shape
    window = (support_size(th), support_size(tw))
    ky, kx = binomial_kernel(window[0]), binomial_kernel(window[1])
    censored = inp.censored
    valid = (~censored).view(np.uint8).astype(np.float32)
    gain, floor = inp.sensor.effective_gain, inp.sensor.floor_variance

    # L0: shot-noise maximum likelihood, sum(s) / sum(e) over uncensored pixels.
    exposure_sum = smooth(inp.exposure * valid, ky, kx)
    has_data = exposure_sum > 0
    first = smooth(inp.signal * valid, ky, kx)
    first /= at_least(exposure_sum.copy(), 1e-30)
    at_least(first, 0.0)
    first *= np.float32(1.0 / gain)  # the weights below need L0 / g only

    radiance = inp.signal / inp.exposure
    numerator = np.zeros(inp.shape, np.float32)
    denominator = np.zeros(inp.shape, np.float32)
    information = np.zeros(inp.shape, np.float32) if return_variance else None
    any_censored = bool(censored.any())
    cross = np.ones(window, np.uint8)
    for exposure, is_level, mask, share, effective in _level_layout(inp.pattern, inp.shape):
        level_censored = censored & is_level if any_censored else None
        if level_censored is not None and level_censored.all():
            continue
        weight = first * np.float32(exposure)
        weight += np.float32(floor)
        np.divide(np.float32(exposure * exposure), weight, out=weight)
        if level_censored is not None and level_censored.any():
            near = cv2.dilate(level_censored.view(np.uint8), cross, borderType=cv2.BORDER_REFLECT_101)
            np.copyto(weight, 0, where=near.view(bool))
        cv2.accumulateProduct(smooth(radiance * mask, ky, kx), weight, numerator)
        weight *= share
        denominator += weight
        if information is not None:
            cv2.accumulateProduct(weight, effective / share, information)
    usable = denominator > 0
    image = first
    image *= np.float32(gain)
    np.divide(numerator, denominator, out=image, where=usable)
    np.maximum(image, 0, out=image)
    if not usable.all():
        # Fallback pixels (every level censored somewhere in the window) hold L0, which
        # only the uncensored, darker side of an edge informs; a censored pixel there
        # knows it is at least its own bound, so it keeps that.
        where = np.nonzero(~usable & censored)
        image[where] = np.maximum(image[where], inp.signal[where] / inp.exposure[where])

    variance = None
    if information is not None:
        variance = (image + floor) / np.maximum(exposure_sum, 1e-30)  # shot + read noise of L0
        np.divide(1.0, information, out=variance, where=usable)
    lower_bound = ~has_data
    if not has_data.all():
        where = np.nonzero(lower_bound)
        image[where] = censored_lower_bound(inp, window)[where]
        if variance is not None:  # a bound is known to within itself: relative error 1
            variance[where] = image[where] ** 2
    return Estimate(image, lower_bound, variance)
