"""``adaptive``: each pixel's own reading where it measures the scene, its neighbours where they agree with it.

Every uncensored pixel i gives an unbiased reading x_i = s_i / e_i of the
radiance at its own position, with the variance of the Poisson-Gaussian model
(sensor.py) v_i = (e_i L / g + sigma^2) / e_i^2, evaluated at a pilot L0 (the
shot-noise maximum-likelihood sum(s) / sum(e) over the window). Per pixel p:

1. Neighbour estimate m: the inverse-variance mean of the readings in a
   binomial window around p *without p itself*, m = sum G_i w_i x_i / sum G_i w_i
   (w_i = 1 / v_i), with variance v_m = sum G^2 / sum G_i w_i. Its error is
   noise plus the bias of structure inside the window (an edge, texture).
2. Local evidence of that bias: the residuals r_i = x_i - m_i of the pixels
   around p. For a flat scene E[r^2] = v_i + v_m; the excess is the squared
   bias. b^2 is its inverse-variance weighted mean over the window (weights
   1 / (v_i + v_m)^2, the inverse variance of r^2), floored at 0.
3. The result is the minimum-mean-square combination of p's own reading and m:
   L = (x_p / v_p + m / (v_m + b^2)) / (1 / v_p + 1 / (v_m + b^2)).
   In flat regions b^2 ~ 0 and the window is averaged with noise-optimal
   weights; where the neighbours disagree with the pixel beyond their noise
   (edges, texture) b^2 grows and a well-exposed pixel keeps its own reading at
   full resolution; a noisy reading (short exposure, low light) counts for
   little either way. No threshold is tuned to images: every quantity is a
   variance of the noise model or a moment of the local residuals.

Censoring. A censored reading only says L >= T_k = censor / e_k. Its pixel
takes the plain (equal-weight) window mean of the uncensored neighbours whose
readings are consistent with that bound (x_i + 2 sqrt(v_i) >= T_k: a 2-sigma
test, the one fixed significance level of the method), and at least T_k.
Equal weights there, because next to a censored pixel the surviving readings
are the darker ones, and noise weights at their own radiance would favour
them further. An uncensored pixel next to a censored pixel of lower or equal
exposure is the dark side of an edge (it survived where a shorter exposure
saturated), so it is left out of its neighbours' estimates m (it still gives
its own pixel's reading). Where a censored pixel has no consistent neighbour,
or the window holds no uncensored reading, the result is the largest lower
bound the window's censored pixels imply, flagged in ``lower_bound``.

Cost. Per-pixel weights make the cost independent of the number of exposure
levels: two separable windows for the pilot, two for m, two for b^2. The
censored-pixel step (one more pair of windows per level) runs only for the
levels, and the rows of each strip, that actually hold censored pixels, so a
scene whose range fits in the unsaturated exposures does not pay for it.
"""

from __future__ import annotations

from concurrent.futures import Executor

import cv2
import numpy as np

from svelive.methods.base import (Estimate, SveInput, at_least, binomial_kernel, censored_lower_bound, in_strips,
                                  smooth, support_size)

#: Significance, in standard deviations of a reading, of "consistent with a censored bound".
CONSISTENT_SIGMA = 2.0
TINY = 1e-12  # floor of sums of inverse variances (real ones exceed 1e-7)
BIG = 1e30  # exposure given to censored pixels when looking for uncensored ones


def kernels(pattern_shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Binomial (rows, cols) kernels, float32: the tile's support, at least 3 taps so every pixel has neighbours."""
    th, tw = pattern_shape
    return binomial_kernel(max(support_size(th), 3)), binomial_kernel(max(support_size(tw), 3))


def run(inp: SveInput, *, return_variance: bool = False, workers: int | Executor = 1) -> Estimate:
    """``workers``: a thread count or an Executor for the frame's strips (base.map_on); the result does not depend on it."""
    ky, kx = kernels(inp.pattern.shape)
    halo = 3 * (max(len(ky), len(kx)) // 2)  # pilot, neighbour estimate, bias: three windows deep
    return in_strips(_run, inp, halo, rows=64, workers=workers, return_variance=return_variance)


def own_share(inp: SveInput) -> np.ndarray:
    """The per-pixel choice: weight of the pixel's own reading in the result, float32 (H, W) in [0, 1].

    1 means the pixel's own reading alone (full resolution), 0 means its
    neighbours alone (censored pixels, or readings far noisier than the
    neighbourhood's average); in between, the noise-optimal blend.
    """
    return _solve(inp, want_share=True)[3]


def _run(inp: SveInput, *, return_variance: bool = False) -> Estimate:
    image, lower, variance, _ = _solve(inp, want_variance=return_variance)
    return Estimate(image, lower, variance)


def _solve(inp: SveInput, want_variance: bool = False, want_share: bool = False):
    """Core of the method on a whole frame or strip: (image, lower_bound, variance or None, share or None)."""
    ky, kx = kernels(inp.pattern.shape)
    f32 = np.float32
    gain_inv, floor = f32(1.0 / inp.sensor.effective_gain), f32(inp.sensor.floor_variance)
    e, s, censored = inp.exposure, inp.signal, inp.censored
    any_censored = bool(censored.any())
    if any_censored:
        s = s.copy()
        np.copyto(s, 0, where=censored)
        e_valid = e.copy()
        np.copyto(e_valid, 0, where=censored)
    else:
        e_valid = e

    # Pilot: shot-noise ML radiance over the window.
    exposure_sum = smooth(e_valid, ky, kx)
    pilot = smooth(s, ky, kx)
    pilot /= at_least(exposure_sum.copy(), TINY)
    at_least(pilot, 0.0)

    # Inverse variance of every reading at its pilot; 0 for censored readings.
    w = pilot * e
    w *= gain_inv
    w += floor
    np.divide(e * e_valid, w, out=w)
    x = inp.signal / e

    # Neighbour estimate without the pixel itself; no neighbours: m = 0 with a huge variance.
    centre = f32(ky[len(ky) // 2] * kx[len(kx) // 2])
    wn = w
    if any_censored:
        censored_exposure = np.full_like(e, BIG)
        np.copyto(censored_exposure, e, where=censored)
        lowest = cv2.erode(censored_exposure, np.ones((len(ky), len(kx)), np.uint8),
                           borderType=cv2.BORDER_REFLECT_101)
        wn = w.copy()
        np.copyto(wn, 0, where=lowest <= e)
    wx = wn * x
    sum_w = smooth(wn, ky, kx)
    sum_w -= centre * wn
    at_least(sum_w, TINY)
    m = smooth(wx, ky, kx)
    m -= centre * wx
    m /= sum_w
    var_m = np.divide(f32((ky * ky).sum() * (kx * kx).sum()), sum_w, out=sum_w)

    # Squared bias of m from the residuals around p, each weighted by the inverse variance of r^2.
    var_p = np.divide(f32(1.0), at_least(w.copy(), TINY))  # censored: ~1 / tiny, so no evidence
    var_r = var_p + var_m
    d = x - m
    excess = d * d
    excess -= var_r
    q = np.multiply(var_r, var_r, out=var_r)
    np.divide(f32(1.0), q, out=q)
    excess *= q
    excess = smooth(excess, ky, kx)
    excess /= at_least(smooth(q, ky, kx), TINY)
    at_least(excess, 0.0)
    excess += var_m  # squared bias + variance of m

    # Minimum-mean-square blend of the own reading and the neighbour estimate: m + (x - m) w / (w + 1 / excess).
    weight_m = np.divide(f32(1.0), excess, out=excess)
    total = weight_m + w
    share = np.divide(w, total, out=weight_m)
    d *= share
    image = np.add(m, d, out=m)

    lower = exposure_sum <= 0
    if any_censored:
        lower |= _censored_pixels(inp, image, x, w, var_p, ky, kx)  # there, image = m (w = 0)
    at_least(image, 0.0)
    variance = np.divide(f32(1.0), total) if want_variance else None
    if lower.any():
        bound = censored_lower_bound(inp, (len(ky), len(kx)))
        np.copyto(image, bound, where=lower)
        if variance is not None:  # a bound is known to within itself: relative error 1
            np.copyto(variance, bound * bound, where=lower)
    return image, lower, variance, share if want_share else None


def _censored_pixels(inp: SveInput, image: np.ndarray, x: np.ndarray, w: np.ndarray, var_p: np.ndarray,
                     ky: np.ndarray, kx: np.ndarray) -> np.ndarray:
    """Set ``image`` at censored pixels, in place; returns the pixels left as bounds only, bool (H, W).

    A censored pixel takes the plain (equal-weight) window mean of the
    uncensored neighbours consistent with its bound (x_i + 2 sigma_i >= bound),
    and at least the bound. Equal weights, because noise weights at each
    neighbour's own radiance favour the darker neighbours, and next to a
    censored pixel the surviving ones are the darker ones. With no consistent
    neighbour the pixel is returned for the caller to give it the largest bound
    of its window.
    """
    f32 = np.float32
    censored = inp.censored
    reach = np.sqrt(var_p)
    reach *= f32(CONSISTENT_SIGMA)
    reach += x  # censored readings have var_p ~ 1 / tiny: an infinite reach, excluded by w > 0 below
    valid = (w > 0).astype(f32)
    rows = np.flatnonzero(censored.any(axis=1))
    ry = len(ky) // 2
    band = slice(max(rows[0] - ry, 0), min(rows[-1] + ry + 1, inp.shape[0]))  # the rows the sums need
    e = inp.exposure[band]
    index = inp.pattern.level_index_map(inp.shape)[band] if inp.pattern.pixel_map is not None else None
    bound_only = np.zeros(inp.shape, bool)
    for k, level in enumerate(inp.pattern.levels.tolist()):
        at = censored[band] & ((e == f32(level)) if index is None else (index == k))
        if not at.any():
            continue
        consistent = valid[band].copy()
        np.copyto(consistent, 0, where=reach[band] < f32(inp.sensor.censor_level / level))
        total = smooth(consistent, ky, kx)
        consistent *= x[band]
        mean = smooth(consistent, ky, kx)
        mean /= at_least(total.copy(), TINY)
        np.maximum(mean, x[band], out=mean)
        np.copyto(image[band], mean, where=at)
        bound_only[band] |= at & (total <= 0)
    return bound_only
