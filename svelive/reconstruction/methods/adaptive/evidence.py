"""The noise model ``adaptive`` uses: the sensor's, with its signal-independent floor from the frame's own evidence
(pairs of same-phase readings a tile apart in dark regions; see :func:`noise_model`)."""

from __future__ import annotations

import numpy as np

from svelive.core.sensor import QUANTISATION_VARIANCE
from svelive.jit import kernel
from svelive.reconstruction.methods.base import SveInput


#: Rows of a frame the noise evidence looks at (spread over the frame and the tile's phases).
EVIDENCE_ROWS = 32
#: The quantile of the pairs' normalised squared differences the noise evidence matches, and chi-square(1)'s
#: value there: a low quantile, so that texture (which only adds to a difference) moves it little, and not lower,
#: where integer readings' differences of 0 would take over.
EVIDENCE_QUANTILE, CHI2_1_AT_QUANTILE = 0.25, 0.10153104
#: Fixed-point steps of the floor's evidence (each a partition of the pairs; 3 settle it to about 1 %).
EVIDENCE_ITERATIONS = 3
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
    is mostly the floor (dark readings), the low quantile EVIDENCE_QUANTILE of
    d^2 / (v_i + v_j) is matched to chi-square with one degree of freedom's
    (Gaussian read noise; texture only raises d^2, and little at a low quantile
    and in the dark), and the floor scaled by the ratio, down to the
    quantisation's 1/12 DN^2. A model that assumes too little read noise would
    make noise look like structure and keep it; one that assumes too much
    smooths too much and lifts dark regions (:func:`nonnegative`). The shot
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

    The pairs' squared differences d^2 have the variance S + F k of the model
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
    pairs = np.empty((3, rows.size * (w - tw)), np.float32)
    # readings near the raw range's bottom may have been clipped there (a black level of 0): left out, like censored
    lowest = -float(inp.sensor.black_level) + EVIDENCE_CLIP_SIGMA * np.sqrt(floor)
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
def _pairs(s, e, c, tw, gain_inv, floor, lowest, pairs):
    """For the pixels j = i + tw of each row of (R, W) arrays where both are uncensored, above ``lowest`` and the
    floor part of the
    model's v_i + v_j is larger than its shot part: (x_i - x_j)^2, the shot part S and k = 1 / e_i^2 + 1 / e_j^2,
    packed into the front of the rows of ``pairs`` (3, N); their count."""
    zero, one = np.float32(0.0), np.float32(1.0)
    n = 0
    for r in range(s.shape[0]):
        for i in range(s.shape[1] - tw):
            ei, ej = e[r, i], e[r, i + tw]
            si, sj = s[r, i], s[r, i + tw]
            radiance = max((si + sj) / (ei + ej), zero)
            shot = radiance * gain_inv * (one / ei + one / ej)
            k = one / (ei * ei) + one / (ej * ej)
            if floor * k > shot and not (c[r, i] or c[r, i + tw]) and si > lowest and sj > lowest:
                d = si / ei - sj / ej
                pairs[0, n] = d * d
                pairs[1, n] = shot
                pairs[2, n] = k
                n += 1
    return n
