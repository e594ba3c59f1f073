"""The noise model ``adaptive`` uses: the sensor's, with its signal-independent floor from the frame's own evidence
(pairs of same-phase readings a tile apart in dark regions; see :func:`noise_model`)."""

from __future__ import annotations

import math

import numpy as np

from svelive.core.sensor import QUANTISATION_VARIANCE
from svelive.jit import kernel
from svelive.reconstruction.methods.base import SveInput


#: Rows of a frame the noise evidence looks at (spread over the frame and the tile's phases).
EVIDENCE_ROWS = 32
#: The quantile of the pairs' differences the noise evidence matches (a low one, so that texture, which only
#: adds to a difference, moves it little), and chi-square(1)'s value there (readings that are not integers:
#: their normalised squared differences).
EVIDENCE_QUANTILE, CHI2_1_AT_QUANTILE = 0.25, 0.10153104
#: Fixed-point steps of the floor's evidence of readings that are not integers (each a partition of the pairs;
#: 3 settle it to about 1 %).
EVIDENCE_ITERATIONS = 3
#: Integer readings: bins of the pairs' shot parts the model's probability is summed over (:func:`_read_variance`),
#: and bisection steps of the read noise variance (from an upper bound: to 2^-40 of it).
LATTICE_BINS, LATTICE_STEPS = 32, 40
#: Integer readings: the tent max(0, K - |d|) whose mean over the pairs is matched has K this many times m + 1, m
#: the EVIDENCE_QUANTILE quantile of |d| (2: about the differences' lower half counts, each the less the larger).
LATTICE_SPAN = 2
#: Readings within this many of the model's floor deviations of the raw range's bottom (raw 0) are left out of
#: the evidence: their noise may have been clipped there.
EVIDENCE_CLIP_SIGMA = 3.0
#: Fewest pairs the noise evidence needs.
EVIDENCE_PAIRS = 256


def noise_model(inp: SveInput) -> tuple[float, float]:
    """The noise model the method uses: (1 / gain, floor variance), float.

    The sensor's model with its signal-independent part (read noise and
    quantisation) taken from the frame's own evidence where the frame has it:
    horizontally adjacent pixels of one tile phase (a tile width apart) read the
    same radiance up to texture, so d = x_i - x_j has the variance v_i + v_j of
    the model where the model is right. Among the pairs whose predicted variance
    is mostly the floor (dark readings), a low quantile (EVIDENCE_QUANTILE) of
    the differences is matched to the model's (Gaussian read noise; texture only
    raises |d|, and little at a low quantile and in the dark): for integer
    readings the mean of a tent max(0, K - |d|) reaching a little beyond the
    quantile (a lattice point) to that of two rounded readings; for others d^2 /
    (v_i + v_j)'s to chi-square with one degree of freedom's
    (:func:`floor_evidence`). The floor is at least the quantisation's 1/12 DN^2.
    A model that assumes too little read noise would make noise look like
    structure and keep it; one that assumes too much smooths too much and lifts
    dark regions (:func:`nonnegative`). The shot
    part is left to the model: where shot noise dominates, the readings are
    bright and texture at a tile's distance outweighs the noise in most pairs of
    real scenes (measured on the shared images: the same statistic came out 1.4
    to over 100 times the true shot variance).
    """
    sensor = inp.sensor
    floor = sensor.floor_variance
    gain_inv = 1.0 / sensor.effective_gain
    return gain_inv, max(floor * floor_evidence(inp, gain_inv, floor), QUANTISATION_VARIANCE)


def floor_evidence(inp: SveInput, gain_inv: float, floor: float) -> float:
    """The frame's signal-independent noise variance over the model's ``floor`` (see :func:`noise_model`);
    1 where fewer than EVIDENCE_PAIRS pairs tell.

    Integer readings of the tile's own exposures (``inp.integral``, not folded),
    whose same-phase pairs have equal exposures: a pair's readings are
    x = round(a + Z), a the expected reading (the same for both up to texture), Z
    Gaussian with the read noise variance r plus the reading's shot part. With the
    fraction of a uniform over the pairs (the frame's many levels), D = x_i - x_j
    takes the integer d with probability h(d), h the density of N(0, s^2)
    convolved with the triangle on [-1, 1] (the difference of the two rounding
    errors of one a), s^2 = 2 r + S, S the pair's shot part in raw DN^2; so
    P(|D| <= k) = 2 (psi(k + 1) - psi(k)) - 1, psi(y) = y Phi(y / s) + s phi(y / s),
    and the tent's mean E max(0, K - |D|) = sum over k < K of P(|D| <= k)
    = 2 (psi(K) - psi(0)) - K for a whole K. K is LATTICE_SPAN (m + 1), m the
    EVIDENCE_QUANTILE quantile of |D| (a lattice point; pairs beyond K, such as
    texture's, count 0), and r the read noise variance at which the mean of the
    model's tent over the pairs is the pairs' (:func:`_read_variance`; 0 where
    even r = 0 predicts less); the floor is r + 1/12, the variance of a rounded
    reading about a. The pairs are chosen by their outer neighbours
    (:func:`_lattice_pairs`). Matching the quantile of d^2 / v to chi-square(1)'s
    instead, as if the readings were continuous, lands on the lattice of integer
    differences: 0.67 of the true floor at 2.7 DN read noise, the quantisation's
    1/12 alone at 0.6 DN.

    Other readings (not integers, or folded exposures: a pair of two colours):
    the pairs' squared differences d^2 have the variance S + F k of the model
    (S its shot part, k = 1 / e_i^2 + 1 / e_j^2) with the frame's floor F in
    place of the model's: F is the fixed point of F <- F Q(d^2 / (S + F k)) / chi2,
    Q the EVIDENCE_QUANTILE, chi2 chi-square(1)'s value there (EVIDENCE_ITERATIONS steps from the model's floor).
    """
    h, w = inp.shape
    tw = inp.period[1]
    if w <= tw:
        return 1.0
    rows = np.unique(np.linspace(0, h - 1, min(h, EVIDENCE_ROWS)).round().astype(np.intp))
    s, e, c = inp.signal[rows], inp.exposure[rows], inp.censored[rows]
    # readings near the raw range's bottom may have been clipped there (a black level of 0): left out, like censored
    lowest = -float(inp.sensor.black_level) + EVIDENCE_CLIP_SIGMA * np.sqrt(floor)
    if inp.integral and not inp.folded:
        pairs = np.empty((2, rows.size * (w - tw)), np.float32)
        count = _lattice_pairs(s, e, c, tw, np.float32(gain_inv), np.float32(floor), np.float32(lowest), pairs)
        if count < EVIDENCE_PAIRS:
            return 1.0
        difference, total = np.abs(pairs[0, :count]), pairs[1, :count]
        at = int(EVIDENCE_QUANTILE * (count - 1))
        span = LATTICE_SPAN * (float(np.partition(difference, at)[at]) + 1.0)
        tent = float(np.maximum(span - difference, 0).mean())
        read = _read_variance(total, span, tent, max(float(floor), span * span), float(gain_inv))
        return (read + QUANTISATION_VARIANCE) / floor
    pairs = np.empty((3, rows.size * (w - tw)), np.float32)
    count = _pairs(s, e, c, tw, np.float32(gain_inv), np.float32(floor), np.float32(lowest), pairs)
    if count < EVIDENCE_PAIRS:
        return 1.0
    square, shot, k = pairs[:, :count]
    at = int(EVIDENCE_QUANTILE * (count - 1))
    level = np.float32(floor)
    ratio = np.empty(count, np.float32)
    for _ in range(EVIDENCE_ITERATIONS):
        np.divide(square, shot + level * k, out=ratio)
        level = max(level * np.float32(np.partition(ratio, at)[at] / CHI2_1_AT_QUANTILE),
                    np.float32(QUANTISATION_VARIANCE))
    return float(level) / floor


@kernel
def _psi(y, s):
    """y Phi(y / s) + s phi(y / s), the second antiderivative of N(0, s^2)'s density."""
    t = y / s
    return y * 0.5 * math.erfc(-t / math.sqrt(2.0)) + s * math.exp(-0.5 * t * t) / math.sqrt(2.0 * math.pi)


@kernel
def _tent(span, s2):
    """E max(0, K - |x_i - x_j|) for a whole K = ``span`` >= 1 and x = round(a + Z) of one a with a uniform
    fraction, Z_i - Z_j ~ N(0, s2): 2 (psi(K) - psi(0)) - K (:func:`floor_evidence`); K at s2 = 0."""
    if s2 <= 0.0:
        return span
    s = math.sqrt(s2)
    return 2.0 * (_psi(span, s) - _psi(0.0, s)) - span


@kernel
def _read_variance(shot, span, tent, start, gain_inv):
    """The read noise variance r >= 0 at which the mean over the pairs of the model's tent (:func:`_tent` of ``span``,
    s^2 = 2 r + the pair's shot part) is ``tent``: bisection (LATTICE_STEPS) in [0, a bound doubled from ``start``].

    ``shot`` is each pair's s_i + s_j over the gain: its shot part (given the pair's electrons, exactly so) plus
    the read noise and rounding of the sum, which is independent of the difference and of variance (2 r + 1/6) /
    gain^2. The pairs are summed in LATTICE_BINS bins of ``shot``, each at its pairs' mean shrunk towards the mean
    of all by that noise's share of the variance of ``shot`` (the expected shot part of the bin's pairs), at least 0.
    """
    bins = LATTICE_BINS
    n = shot.size
    bottom, top, mean, square = np.inf, -np.inf, 0.0, 0.0
    for i in range(n):
        x = float(shot[i])
        bottom = min(bottom, x)
        top = max(top, x)
        mean += x
        square += x * x
    mean /= n
    spread = max(square / n - mean * mean, 0.0)
    total = np.zeros(bins)
    number = np.zeros(bins)
    scale = bins / (top - bottom) if top > bottom else 0.0
    for i in range(n):
        b = min(int((shot[i] - bottom) * scale), bins - 1)
        total[b] += shot[i]
        number[b] += 1.0
    used = 0
    for b in range(bins):  # the occupied bins to the front: their mean s_i + s_j over the gain and share of pairs
        if number[b] > 0.0:
            total[used] = total[b] / number[b]
            number[used] = number[b] / n
            used += 1

    def predicted(r):
        noise = (2.0 * r + 2.0 * QUANTISATION_VARIANCE) * gain_inv * gain_inv
        keep = max(1.0 - noise / spread, 0.0) if spread > 0.0 else 0.0
        p = 0.0
        for b in range(used):
            p += number[b] * _tent(span, 2.0 * r + max(mean + keep * (total[b] - mean), 0.0))
        return p

    if predicted(0.0) <= tent:
        return 0.0
    high = start
    for _ in range(200):
        if predicted(high) < tent:
            break
        high *= 2.0
    low = 0.0
    for _ in range(LATTICE_STEPS):
        mid = 0.5 * (low + high)
        if predicted(mid) > tent:
            low = mid
        else:
            high = mid
    return 0.5 * (low + high)


@kernel
def _pairs(s, e, c, tw, gain_inv, floor, lowest, pairs):
    """For the pixels j = i + tw of each row of (R, W) arrays where both are uncensored, above ``lowest`` and the
    floor part of the
    model's v_i + v_j is larger than its shot part: (x_i - x_j)^2, the shot part S and k = 1 / e_i^2 + 1 / e_j^2,
    packed into the front of the rows of ``pairs`` (3, N); their count."""
    zero, one = np.float32(0.0), np.float32(1.0)
    m = s.shape[1] - tw
    # a row's every pair first, in a loop without branches (its divisions vectorise), then the chosen ones packed
    square, shots, ks, chosen = np.empty(m, np.float32), np.empty(m, np.float32), np.empty(m, np.float32), \
        np.empty(m, np.bool_)
    n = 0
    for r in range(s.shape[0]):
        for i in range(m):
            ei, ej = e[r, i], e[r, i + tw]
            si, sj = s[r, i], s[r, i + tw]
            radiance = max((si + sj) / (ei + ej), zero)
            shot = radiance * gain_inv * (one / ei + one / ej)
            k = one / (ei * ei) + one / (ej * ej)
            d = si / ei - sj / ej
            square[i], shots[i], ks[i] = d * d, shot, k
            chosen[i] = (floor * k > shot) & ~(c[r, i] | c[r, i + tw]) & (si > lowest) & (sj > lowest)
        for i in range(m):
            if chosen[i]:
                pairs[0, n] = square[i]
                pairs[1, n] = shots[i]
                pairs[2, n] = ks[i]
                n += 1
    return n


@kernel
def _lattice_pairs(s, e, c, tw, gain_inv, floor, lowest, pairs):
    """For the pixels j = i + tw of each row of (R, W) arrays of integer readings where both and their outer
    neighbours i - tw, j + tw (of the same phases) are uncensored, the neighbours' sum is above twice ``lowest``
    and the floor part of the model's v_i + v_j at the neighbours' radiance is larger than its shot part: the
    difference s_i - s_j and (s_i + s_j) / gain, packed into the front of the rows of ``pairs`` (2, N); their
    count. The pairs are chosen by their neighbours, not by their own readings: an integer sum and difference
    have one parity, so a choice by the sum would choose differences (and one by each reading, as the clipping
    guard of :func:`_pairs`, cuts the differences of pairs near the bound)."""
    zero, one = np.float32(0.0), np.float32(1.0)
    n = 0
    for r in range(s.shape[0]):
        for i in range(tw, s.shape[1] - 2 * tw):
            j = i + tw
            if c[r, i] or c[r, j] or c[r, i - tw] or c[r, j + tw]:
                continue
            ei, ej = e[r, i], e[r, j]
            outer = s[r, i - tw] + s[r, j + tw]
            level = outer / (e[r, i - tw] + e[r, j + tw])
            shot = max(level, zero) * gain_inv * (one / ei + one / ej)
            if floor * (one / (ei * ei) + one / (ej * ej)) > shot and outer > lowest + lowest:
                pairs[0, n] = s[r, i] - s[r, j]
                pairs[1, n] = (s[r, i] + s[r, j]) * gain_inv
                n += 1
    return n
