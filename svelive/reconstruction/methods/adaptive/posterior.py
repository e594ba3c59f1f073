"""Step 4 of ``adaptive``: radiance is not negative. exp(E[log L]) of the estimate's normal restricted to L >= 0
(:func:`nonnegative`, a polynomial fitted to :func:`posterior_table`), where the estimate lies near 0."""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from svelive.jit import kernel
from svelive.memory import outside_heap
from svelive.reconstruction.methods.adaptive.parameters import TINY
from svelive.reconstruction.methods.base import count_true, true_positions


@kernel
def posterior_at(changed, estimate, information, image, coefficients, variance):
    """image = step 4's result of (estimate, information) at the ``changed`` pixels of (R, W) arrays, variance =
    1 / information there unless ``variance`` is empty. Row by row: a row with many (DENSE_CHANGED or more of
    its pixels) whole, each pixel's result chosen in the same loop without branches (:func:`_nonnegative_where`);
    a row with fewer packed into short arrays first (base.true_positions: without a branch per pixel, since the wide
    fallback's pixels lie scattered and such a branch mispredicts)."""
    width = changed.shape[1]
    packed_image = np.empty(width, np.float32)
    packed_estimate, packed_information = np.empty(width, np.float32), np.empty(width, np.float32)
    index = np.empty(width, np.int64)
    one = np.float32(1.0)
    for r in range(changed.shape[0]):
        row = changed[r]
        n = count_true(row)
        if n == 0:
            continue
        row_estimate, row_information, target = estimate[r], information[r], image[r]
        if n >= DENSE_CHANGED * width:
            _nonnegative_where(target, row_estimate, row_information, row, coefficients)
            if variance.size > 0:
                row_variance = variance[r]
                for c in range(width):
                    kept, new = row_variance[c], one / row_information[c]
                    row_variance[c] = new if row[c] else kept
            continue
        n = true_positions(row, n, index)
        for j in range(n):
            value = row_estimate[index[j]]
            packed_estimate[j], packed_information[j], packed_image[j] = value, row_information[index[j]], value
        nonnegative(packed_image[:n], packed_estimate[:n], packed_information[:n], coefficients)
        for j in range(n):
            target[index[j]] = packed_image[j]
        if variance.size > 0:
            row_variance = variance[r]
            for j in range(n):
                row_variance[index[j]] = one / packed_information[j]


#: :func:`posterior_at` takes a row whole where at least this share of its pixels changed, else packs them. The
#: wide fallback's calls on nine dim and bright bench frames, recorded, 1920x1200: a whole row costs about 2.3 us at
#: any share, a packed row about 1 us and 10 ns a pixel; 0.2 -> 0.07 took the rows at 7-20 %
#: whole: StarField 1/1/8/8 dim (18 % changed) 3.6 -> 2.8 ms, Garden 1/1/8/8 dim (10 %) 3.8 -> 2.8, Desk 1,4/16,64
#: dim 3.3 -> 2.7; frames of rows at 1-2 % (StarField 1/1/8/8 bright) unchanged.
DENSE_CHANGED = 0.07


#: The fused pass (strip_pass) runs :func:`nonnegative` only where pixels near 0 are when fewer than one in this
#: many are.
FEW_NEAR_ZERO = 4
#: Margin of the test for the pixels :func:`nonnegative` may change (L^ <= 0, or L^^2 information below
#: POSTERIOR_HIGH^2 times it) over its own: z = L^ sqrt(information) < POSTERIOR_HIGH, rounded to float32, implies
#: L^^2 information < POSTERIOR_HIGH^2 (1 + 1e-6) rounded, so this margin misses none.
NEAR_MARGIN = 1.0 + 1e-5


#: The range of z = estimate / sigma over which :func:`posterior_table` tabulates, and its step. From
#: POSTERIOR_HIGH up the result is the estimate itself: exp(E[log L]) is below it by 1/(2 z^2), under 0.08 %.
POSTERIOR_LOW, POSTERIOR_HIGH, POSTERIOR_STEP = -30.0, 25.0, 1.0 / 16
#: Degree of the polynomial :func:`posterior_polynomial` fits (5e-4 relative error at most, float32); the kernel
#: (:func:`nonnegative`) writes out its Horner scheme for this degree.
POSTERIOR_DEGREE = 16
EULER_GAMMA = 0.5772156649015329
#: exp(-Euler's gamma): exp(E[log L]) of an exponential distribution of mean 1.
TAIL = math.exp(-EULER_GAMMA)


#: Rows of z :func:`posterior_table` integrates at once. The whole grid at once (881 rows x 12000) made five float64
#: temporaries of 85 MB at a process's first adaptive frame, which set the service's peak resident memory.
POSTERIOR_CHUNK = 32


@lru_cache(maxsize=1)
def posterior_table() -> np.ndarray:
    """g(z) = exp(E[log L]) for L ~ N(z, 1) restricted to L > 0, at z = POSTERIOR_LOW + i POSTERIOR_STEP up to
    POSTERIOR_HIGH; float64, read-only. Integrated over u = log L (the integrand is smooth there), POSTERIOR_CHUNK
    values of z at a time (a row's sums are the same whatever the chunk) in two buffers of pages of their own,
    unmapped afterwards: computed once, it leaves nothing in malloc's heap (``svelive.memory``)."""
    z = np.arange(POSTERIOR_LOW, POSTERIOR_HIGH + POSTERIOR_STEP / 2, POSTERIOR_STEP)[:, None]
    u = np.linspace(-50.0, np.log(POSTERIOR_HIGH + 14.0), 12000)[None, :]
    level = np.exp(u)
    table = np.empty(len(z))
    chunk = min(POSTERIOR_CHUNK, len(z))
    density_of, weighted_of = (outside_heap((chunk, u.size), np.float64) for _ in range(2))
    for start in range(0, len(z), chunk):
        rows = z[start:start + chunk]
        density, weighted = density_of[:len(rows)], weighted_of[:len(rows)]
        # phi(L - z) dL, times phi(0) / phi(z) below 0 (no underflow there; the scale cancels), term by term as
        # exp(-0.5 * (level - z) ** 2 + 0.5 * np.minimum(z, 0) ** 2 + u)
        np.subtract(level, rows, out=density)
        np.square(density, out=density)
        np.multiply(-0.5, density, out=density)
        np.add(density, 0.5 * np.minimum(rows, 0) ** 2, out=density)
        np.add(density, u, out=density)
        np.exp(density, out=density)
        np.multiply(u, density, out=weighted)
        table[start:start + chunk] = np.exp(weighted.sum(axis=1) / density.sum(axis=1))
    table.setflags(write=False)
    return table


def posterior_base(z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(b, u) of :func:`posterior_polynomial`: b(z) = (z + r) / 2 = c / ((r - z) / 2), r = sqrt(z^2 + 4c),
    c = TAIL, and u = z / r in (-1, 1); float64."""
    root = np.sqrt(z * z + 4 * TAIL)
    return np.where(z > 0, (z + root) / 2, 2 * TAIL / (root - np.minimum(z, 0))), z / root


@lru_cache(maxsize=1)
def posterior_polynomial() -> np.ndarray:
    """Coefficients (lowest first, float32 (POSTERIOR_DEGREE + 1,), read-only) of P(u) with g(z) = b(z) P(u)
    (:func:`posterior_base`) for z < POSTERIOR_HIGH: least squares on :func:`posterior_table` and, below it, the
    expansion g(z) = e^-gamma / |z| (1 - 1.5 / z^2) (the normal restricted to L > 0 is nearly exponential there).

    b has g's asymptotes (z, and e^-gamma / |z|), so P is smooth and near 1 over the whole line, and the kernel
    evaluates it without a table look-up (which does not vectorise).
    """
    z_table = np.arange(POSTERIOR_LOW, POSTERIOR_HIGH + POSTERIOR_STEP / 2, POSTERIOR_STEP)
    z_tail = -np.geomspace(3000.0, -POSTERIOR_LOW, 200)[:-1]
    tail = TAIL / -z_tail * (1 - 1.5 / z_tail**2)
    z = np.concatenate([z_tail, z_table])
    base, u = posterior_base(z)
    coefficients = np.polynomial.polynomial.polyfit(u, np.concatenate([tail, posterior_table()]) / base,
                                                    POSTERIOR_DEGREE).astype(np.float32)
    coefficients.setflags(write=False)
    return coefficients


@kernel
def nonnegative(image, estimate, information, coefficients):
    """image = exp(E[log L]) for L ~ N(estimate, 1 / information) restricted to L > 0 (a flat prior on L >= 0):
    sigma g(z), z = estimate / sigma, where z < POSTERIOR_HIGH (``image`` holds the estimate beyond); flat arrays.

    Radiance cannot be negative, and the project judges errors in log radiance (log-PSNR, PU21, stops): the
    estimate that minimises the expected squared error of log L is exp(E[log L]). Where a reading lies within a few
    noise deviations of 0 it is a small positive value (about half a deviation at 0) instead of 0: clipping at 0
    gives exact zeros, errors of many stops; the mean and the median of the restricted normal lie higher, and
    overshoot regions far darker than the noise more. Above 0 it is below the estimate by about 1 / (2 z^2) (3 % at
    z = 4, 0.5 % at z = 10); from POSTERIOR_HIGH up, the estimate itself. g = b(z) P(u)
    (:func:`posterior_polynomial`, ``coefficients``); without branches, so that LLVM vectorises it.
    """
    p = _terms(coefficients)
    for k in range(image.size):
        value, near = _posterior(estimate[k], information[k], p)
        image[k] = value if near else image[k]


@kernel
def _nonnegative_where(image, estimate, information, where, coefficients):
    """image = :func:`nonnegative`'s result of (estimate, information) where ``where`` (bool), left elsewhere; one
    row, in one loop (the choice without branches: both values loaded first, so that LLVM vectorises it)."""
    p = _terms(coefficients)
    for k in range(image.size):
        value, near = _posterior(estimate[k], information[k], p)
        kept, new = image[k], (value if near else estimate[k])
        image[k] = new if where[k] else kept


@kernel
def _terms(coefficients):
    """The polynomial's POSTERIOR_DEGREE + 1 coefficients as a tuple of float32 (read once before a loop)."""
    return (coefficients[0], coefficients[1], coefficients[2], coefficients[3], coefficients[4], coefficients[5],
            coefficients[6], coefficients[7], coefficients[8], coefficients[9], coefficients[10], coefficients[11],
            coefficients[12], coefficients[13], coefficients[14], coefficients[15], coefficients[16])


@kernel(inline="always")
def _posterior(estimate, information, p):
    """(sigma g(z), z < POSTERIOR_HIGH) of one pixel (:func:`nonnegative`); ``p``: :func:`_terms`. Inlined into
    the loops that call it (a call left in place keeps LLVM from vectorising them)."""
    zero, half, tiny = np.float32(0.0), np.float32(0.5), np.float32(TINY)
    high, c4 = np.float32(POSTERIOR_HIGH), np.float32(4.0 * TAIL)
    root_t = np.sqrt(max(information, tiny))
    z = estimate * root_t
    r = np.sqrt(z * z + c4)
    base = (z + r) * half if z > zero else c4 * half / (r - z)
    u = z / r
    # Horner's scheme written out (a loop over the coefficients would not vectorise): degree POSTERIOR_DEGREE = 16
    q = (((((((((((((((p[16] * u + p[15]) * u + p[14]) * u + p[13]) * u + p[12]) * u + p[11]) * u + p[10]) * u
                    + p[9]) * u + p[8]) * u + p[7]) * u + p[6]) * u + p[5]) * u + p[4]) * u + p[3]) * u + p[2]) * u
         + p[1]) * u + p[0]
    return base * q / root_t, z < high
