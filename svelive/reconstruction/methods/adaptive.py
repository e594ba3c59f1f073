"""``adaptive``: each pixel's own reading where it measures the scene, its neighbours where they agree with it.

Every uncensored pixel i gives an unbiased reading x_i = s_i / e_i of the
radiance at its own position, with the variance of the Poisson-Gaussian model
(sensor.py) v_i = (e_i L / g + sigma^2) / e_i^2, evaluated at a pilot L0 (the
shot-noise maximum-likelihood sum(s) / sum(e) over the window *without pixel
i*: with its own reading in it, a pixel's weight would fall as it reads high,
a bias low). sigma^2, the model's read noise and quantisation, is replaced by
the frame's own evidence where the frame has it (:func:`noise_model`:
pairs of pixels a tile apart in dark regions, a low quantile of their squared
differences against chi-square), so a noise model given wrong, or not given,
does not make noise look like structure. Per pixel p:

1. Neighbour estimate m: the inverse-variance mean of the readings in a
   binomial window around p *without p itself*, m = sum G_i w_i x_i / sum G_i w_i
   (w_i = 1 / v_i), with variance v_m = sum G^2 / sum G_i w_i. Its error is
   noise plus the bias of structure inside the window (an edge, texture).
2. Local evidence of that bias: the residuals r_i = x_i - m_i of the pixels
   around p. For a flat scene E[r^2] = v_i + v_m; the excess is the squared
   bias. B is its inverse-variance weighted mean over the window (weights
   1 / (v_i + v_m)^2, the inverse variance of r^2), with standard error
   SE = sqrt(2 sum G^2 q) / sum G q under a flat scene; b^2 = max(B - 2 SE, 0)
   (CONTRAST_SIGMA): where the window cannot tell structure from noise, b^2 = 0
   and the result is the window's noise-optimal mean.
3. The minimum-mean-square combination of p's own reading and m:
   L^ = (x_p / v_p + m / (v_m + b^2)) / (1 / v_p + 1 / (v_m + b^2)), variance
   1 / (1 / v_p + 1 / (v_m + b^2)). In flat regions the window is averaged with
   noise-optimal weights; where the neighbours disagree with the pixel beyond
   their noise (edges, texture) b^2 grows and a well-exposed pixel keeps its own
   reading at full resolution; a noisy reading (short exposure, low light)
   counts for little either way.
4. Radiance is not negative: within 25 deviations of 0 the result is
   exp(E[log L]) of N(L^, variance) restricted to L >= 0 (:func:`_nonnegative`),
   the estimate that minimises the expected squared error in log radiance
   (stops, as the project's metrics judge), never an exact 0; beyond, L^
   itself. A window whose readings all sit at raw 0 (clipped below) gives 0.
5. Where the result still cannot tell the level from 0 (L^ within
   CONTRAST_SIGMA deviations of it, an uncensored pixel), wider windows that
   are flat within their noise (:func:`_wide_fallback`): the eight blocks of the
   window's size one block away from the pixel, then the eight of three times
   that around them (WIDE_SCALES), each scale's level blended in as in step 3
   with the squared bias its blocks' chi-square shows beyond noise (so bright
   structure a block away counts for little), the next scale only while the
   blocks show no structure and the result still cannot tell the level from 0;
   then step 4. A 3x3 window cannot resolve a level many stops below its noise
   (step 4 then gives about half its deviation, far above such a level); a
   flat region's wider windows can.
No threshold is tuned to images: every quantity is a variance of the noise
model, a moment of the local residuals or a fixed significance level.

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
censored-pixel step runs only in the rows holding censored pixels: a 3x3 window
visits each censored pixel once (:func:`_censored_each`) or, in a row with many,
every pixel of the row a tap at a time (vectorised); a 5x3 window (line-interleaved
patterns) computes the per-level window sums at the censored pixels alone
(:func:`_censored_separable`); longer windows get one more pair of windows per
level with censored pixels, over the box around them; so a scene whose range
fits in the unsaturated exposures does not pay for it, nor for the lower-bound
fill, which also follows the rows holding lower bounds. Step 4's polynomial runs
only in rows holding pixels within 25 deviations of 0, on those pixels alone
(packed) where they are few. Step 5 runs only over strips holding pixels it
applies to (and as far as its widest blocks reach): two box filters per scale
where they are many, each pixel summing its own blocks where they are few. The
noise evidence reads 32 rows of the frame.
Steps 1-4 but the censored pixels' own values run as one compiled pass down a
strip's rows (:func:`_fused`, svelive.jit): each window sum a row filter into a
ring of the window's height of rows and a column filter of the ring, each
per-pixel stage (weights w, x, w x; residuals: m, v_m and the two terms whose
windows give b^2; blend: the result, step 4) a window's half height behind the
one it reads, so the strip's intermediate arrays are a few rows in cache, and
each stage computes only the rows the next one reads (the result only in the
rows the strip keeps). Without censored pixels the pilot's exposure window is
the same for every strip of a frame (strips start on whole tiles), so it is
computed once per pattern and strip shape; a folded input (a colour frame's
luminance, see svelive.reconstruction.colour) computes it in the pass, and
tests each censored pixel against its own bound in one compiled pass.
"""

from __future__ import annotations

import math
from concurrent.futures import Executor
from functools import lru_cache
from typing import NamedTuple

import cv2
import numpy as np

from svelive.jit import flat, kernel
from svelive.reconstruction.methods.base import (Estimate, SveInput, binomial_kernel, fill_lower_bounds, map_on,
                                  reflect_101, rows_min, smooth, support_size, window_kernels, window_level_row)
from svelive.pattern import Pattern

#: Significance, in standard deviations of a reading, of "consistent with a censored bound".
CONSISTENT_SIGMA = 2.0
#: Significance, in standard errors of the window's squared-bias estimate, of structure (texture, an edge):
#: the estimate is shrunk by this many standard errors, so where the window cannot tell structure from noise the
#: result is the neighbourhood's noise-optimal mean.
CONTRAST_SIGMA = 2.0
TINY = 1e-12  # floor of sums of inverse variances (real ones exceed 1e-7)
BIG = 1e30  # exposure given to censored pixels when looking for uncensored ones


def kernels(pattern_shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Binomial (rows, cols) kernels, float32: the tile's support, at least 3 taps so every pixel has neighbours."""
    th, tw = pattern_shape
    return binomial_kernel(max(support_size(th), 3)), binomial_kernel(max(support_size(tw), 3))


def run(inp: SveInput, *, return_variance: bool = False, workers: int | Executor = 1,
        window: bool = False) -> Estimate:
    """``workers``: a thread count or an Executor for the frame's strips (base.map_on); the result does not depend on it.

    ``window``: also the motion tests' window mean and its variance (``Estimate.window``), made in the
    same pass from the pilot's window sums, where the method's window is the motion tests' (the same
    kernels, of at most INLINE_WINDOW taps, whose sums are bit-identical); else ``Estimate.window`` is None.
    """
    in_pass = window and _shares_window(inp)
    image, lower, variance, _, _, means = _estimate(inp, noise_model(inp), workers, want_variance=return_variance,
                                                    want_window=in_pass)
    return Estimate(image, lower, variance, window=(means[0], means[1]) if in_pass else None)


#: The longest windows (rows, columns) whose sums the pass makes in the order the motion tests' own kernel does
#: (svelive.reconstruction.numerics.INLINE_TAPS): beyond, the window mean is left to the motion tests.
INLINE_WINDOW = (5, 3)


def _shares_window(inp: SveInput) -> bool:
    """Whether this method's window is the motion tests' (numerics.window_estimate): the same kernels, short enough
    for the same order of sums."""
    ky, kx = kernels(inp.pattern.shape)
    wy, wx = window_kernels(inp.period)[:2]
    return (ky.size <= INLINE_WINDOW[0] and kx.size <= INLINE_WINDOW[1] and np.array_equal(ky, wy)
            and np.array_equal(kx, wx))


#: Rows of a frame the noise evidence looks at (spread over the frame and the tile's phases).
EVIDENCE_ROWS = 32
#: The quantile of the pairs' normalised squared differences the noise evidence matches, and chi-square(1)'s
#: value there: a low quantile, so that texture (which only adds to a difference) moves it little, and not lower,
#: where integer readings' differences of 0 would take over.
EVIDENCE_QUANTILE, CHI2_1_AT_QUANTILE = 0.25, 0.10153104
#: Scales of the wide fallback (:func:`_wide_fallback`): blocks of the window's size, then 3 times it, ...
WIDE_SCALES = 2
#: The wide fallback takes box filters over a band of rows once its active pixels times a block's pixels times
#: this exceed the band's pixels; below, each active pixel sums its eight blocks itself (:func:`_wide_direct`).
#: Eight: a pixel read per block pixel taken to cost about a box-filtered pixel of the band (not tuned).
WIDE_DIRECT = 8
#: Strips the wide fallback takes together (one band of rows, its box filters reaching beyond it only once).
WIDE_GROUP = 4
#: Largest window (taps) whose censored pixels are visited one by one (:func:`_censored_pixels`): measured, a 3x3
#: window's visits beat the per-level window sums at any share of censored pixels, a 5x3 one's did not.
DIRECT_TAPS = 9
#: A row of :func:`_censored_each` or :func:`_censored_separable` with more than one censored pixel in this many
#: sums every pixel's window at once (measured on the benchmark's frames: 32 beat 8 and 96).
DENSE_ROW = 32
#: Variance of rounding to integer DN, the least signal-independent noise a reading has.
QUANTISATION_VARIANCE = 1.0 / 12.0
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
    smooths too much and lifts dark regions (:func:`_nonnegative`). The shot
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


def own_share(inp: SveInput) -> np.ndarray:
    """The per-pixel choice: weight of the pixel's own reading in the result, float32 (H, W) in [0, 1].

    1 means the pixel's own reading alone (full resolution), 0 means its
    neighbours alone (censored pixels, or readings far noisier than the
    neighbourhood's average, or a dark pixel that took a wide window's level);
    in between, the noise-optimal blend.
    """
    return _estimate(inp, noise_model(inp), 1, want_share=True)[3]


def path_shares(inp: SveInput) -> dict[str, float]:
    """Which share of the frame's pixels (rows, strips) takes which of the method's paths, float in [0, 1].

    ``censored``: pixels whose reading is censored (the censored-pixel step computes them);
    ``censored_rows``: rows holding one (the rows that step visits); ``near_zero``: uncensored
    pixels whose L^ lies within POSTERIOR_HIGH deviations of 0 (step 4's polynomial);
    ``wide``: pixels that cannot tell their level from 0 (the wide fallback's candidates) and
    ``wide_strips``: the strips holding one (the fallback's work follows them); ``lower``:
    pixels left at a lower bound; ``plain``: uncensored pixels that take none of these
    (steps 1-3 alone, the closed form). A diagnostic for benchmarks/paths.py: it runs the method.
    """
    _, lower, _, _, darks, _ = _estimate(inp, noise_model(inp), 1)
    estimate = np.concatenate([d.estimate for d in darks])
    information = np.concatenate([d.information for d in darks])
    candidates = np.concatenate([d.candidates for d in darks])
    censored = inp.censored
    high = np.float32(POSTERIOR_HIGH * POSTERIOR_HIGH)
    near = ((estimate <= 0) | (estimate * estimate * information < high)) & ~censored
    n = censored.size
    return {"censored": np.count_nonzero(censored) / n, "censored_rows": float(censored.any(axis=1).mean()),
            "near_zero": np.count_nonzero(near) / n, "wide": np.count_nonzero(candidates) / n,
            "wide_strips": sum(1 for d in darks if d.count) / len(darks), "lower": np.count_nonzero(lower) / n,
            "plain": np.count_nonzero(~(censored | near | candidates | lower)) / n}


class _Dark(NamedTuple):
    """What the wide fallback (:func:`_wide_fallback`) needs of a strip's rows, float32 (rows, W) unless said.

    ``weights``: the readings' inverse variances as the neighbour estimate uses them (wn: 0 where censored or on
    the dark side of an edge); ``estimate`` and ``information``: L^ and 1 / variance of the window's result
    before step 4; ``candidates``: bool, where the result cannot tell the level from 0 (:func:`_candidates`),
    ``count`` of them."""

    weights: np.ndarray
    estimate: np.ndarray
    information: np.ndarray
    candidates: np.ndarray
    count: int

    def rows(self, keep: slice) -> _Dark:
        return _Dark(self.weights[keep], self.estimate[keep], self.information[keep], self.candidates[keep],
                     int(np.count_nonzero(self.candidates[keep])) if self.count else 0)


def _estimate(inp: SveInput, noise: tuple[float, float], workers: int | Executor, want_variance: bool = False,
              want_share: bool = False, want_window: bool = False):
    """The method on a frame: (image, lower_bound, variance or None, share or None, the strips' _Dark, the window
    mean and its variance as a (2, H, W) array, or of no rows without ``want_window``).

    Steps 1-4 run in strips of about 64 rows (a window three deep above and
    below each, as base.in_strips does; the result does not depend on them),
    then the wide fallback over the strips holding pixels that cannot tell
    their level from 0, reading their neighbours' rows as far as its widest
    window reaches."""
    ky, kx = kernels(inp.pattern.shape)
    halo = 3 * (max(len(ky), len(kx)) // 2)  # pilot, neighbour estimate, bias: three windows deep
    spans = _spans(inp, halo, 64)
    h, w = inp.shape
    image, lower = np.empty((h, w), np.float32), np.empty((h, w), bool)
    variance = np.empty((h, w), np.float32) if want_variance else None
    own = np.empty((h, w), np.float32) if want_share else None
    window = np.empty((2, h, w) if want_window else (2, 0, 0), np.float32)

    def strip(span: tuple[int, int, int, int]) -> _Dark:
        # each strip's kept rows copied into the frame's arrays by its own thread (no serial join)
        start, top, bottom, stop = span
        crop = inp if (start, stop) == (0, inp.shape[0]) else inp.crop(slice(start, stop))
        keep = slice(top - start, bottom - start)
        # the window's rows are written only in the kept rows: a view of the frame's array
        pieces = _solve(crop, noise, want_variance, want_share, keep, window[:, start:stop] if want_window else window)
        for whole, piece in zip((image, lower, variance, own), pieces[:4]):
            if whole is not None:
                whole[top:bottom] = piece[keep]
        return pieces[4].rows(keep)

    darks = map_on(workers, strip, spans)
    if WIDE_SCALES > 0 and any(d.count for d in darks):
        _wide_fallback(inp, spans, darks, image, variance, ky, kx, workers)
    share = None
    if want_share:
        share = np.divide(own, _joined([d.information for d in darks]))
    return image, lower, variance, share, darks, window


def _joined(pieces: list[np.ndarray | None]) -> np.ndarray | None:
    """The strips' pieces one below the other (the piece itself when there is one; None when they are None)."""
    if pieces[0] is None:
        return None
    return pieces[0] if len(pieces) == 1 else np.concatenate(pieces)


def _spans(inp: SveInput, halo: int, rows: int) -> list[tuple[int, int, int, int]]:
    """The strips of the frame: (first row read, first row kept, end of rows kept, end of rows read), starting on
    whole tiles (the pattern keeps its phase), ``halo`` rows read beyond the kept ones; one strip where the frame
    is short or its exposures a per-pixel map."""
    th, h = inp.period[0], inp.shape[0]
    halo = -(-halo // th) * th
    rows = max(-(-rows // th) * th, th)
    if h <= rows + 2 * halo or inp.pattern.pixel_map is not None:
        return [(0, 0, h, h)]
    return [(max(top - halo, 0), top, min(top + rows, h), min(top + rows + halo, h)) for top in range(0, h, rows)]


def _solve(inp: SveInput, noise: tuple[float, float], want_variance: bool = False, want_share: bool = False,
           keep: slice | None = None, window: np.ndarray | None = None):
    """Steps 1-4 on a whole frame or strip: (image, lower_bound, variance or None, w or None, _Dark), (H, W)
    arrays whose rows ``keep`` (default all) hold the results; other rows are not set. ``window``: (2, H, W)
    float32 into whose rows ``keep`` the motion tests' window mean and variance go (:func:`_fused`), or None.

    ``noise``: (1 / gain, floor variance) of the noise model (:func:`noise_model`). The window sums and the
    per-pixel arithmetic between them run as one compiled pass (:func:`_fused`), then the censored pixels."""
    ky, kx = kernels(inp.pattern.shape)
    f32 = np.float32
    shape = inp.shape
    first, last = (0, shape[0]) if keep is None else (keep.start, keep.stop)
    e, censored = inp.exposure, inp.censored
    flagged = bool(censored.any())
    exposure_sum = np.empty((0, 0), f32)  # computed in the pass
    if not (flagged or inp.folded):  # the pattern's, the same for every strip (a folded input's vary)
        cached, first_tile = _exposure_sum(inp.pattern, shape)
        if np.array_equal(e[:first_tile.shape[0], :first_tile.shape[1]], first_tile):  # the pattern's phase
            exposure_sum = cached
    w, image, estimate, total = (np.empty(shape, f32) for _ in range(4))
    # with censored pixels, the neighbours' weights wn differ from w, and the censored step reads x
    wn, x = (np.empty(shape, f32), np.empty(shape, f32)) if flagged else (w, np.empty((2 * (len(ky) // 2) + 1,
                                                                                        shape[1]), f32))
    lower, candidates = np.empty(shape, bool), np.empty(shape, bool)
    variance = np.empty(shape if want_variance else (0, 0), f32)
    kernel_square = f32((ky * ky).sum() * (kx * kx).sum())
    count, lowered = _fused(inp.signal, e, censored, flagged, exposure_sum, first, last, ky, kx, f32(noise[0]),
                            f32(noise[1]), f32(ky[len(ky) // 2] * kx[len(kx) // 2]), kernel_square,
                            f32(CONTRAST_SIGMA**2 * 2.0) * kernel_square, posterior_polynomial(),
                            -f32(inp.sensor.black_level), f32(CONTRAST_SIGMA**2),
                            w, wn, x, image, estimate, total, lower, candidates, variance,
                            np.empty((2, 0, 0), f32) if window is None else window,
                            np.array([1.0 / inp.sensor.effective_gain, inp.sensor.floor_variance], f32))
    if flagged:
        bound_only = _censored_pixels(inp, image, w, x, ky, kx)
        lowered = lowered or bool(bound_only.any())
        lower |= bound_only
    if lowered:
        fill_lower_bounds(inp, lower, (len(ky), len(kx)), image, variance if want_variance else None)
    return (image, lower, variance if want_variance else None, w if want_share else None,
            _Dark(wn, estimate, total, candidates, count))


@kernel
def _fused(s, e, censored, flagged, exposure_sum, first, last, ky, kx, gain_inv, floor, centre, kernel_square,
           threshold, coefficients, bottom, z2, w, wn, x, image, estimate, total, lower, candidates, variance,
           window, window_noise):
    """Steps 1-4 but the censored pixels' own values, on the rows [first, last) of (H, W) arrays, in one pass
    down the rows: the chain of :func:`_weights` (:func:`_weights_censored` where ``flagged``: the strip holds
    censored pixels), :func:`_residuals`, :func:`_blend`, :func:`_zero_bottom_row` and
    :func:`_candidates` with their window sums between them, each stage a window's half height behind the one
    it reads, and only on the rows the next one reads.

    Each window sum is a row filter into a ring of the window's height of filtered rows, then a column filter
    of the ring's rows (:func:`_row_filter`, :func:`_column_filter`: ``smooth``'s arithmetic and borders,
    reflect-101 at the array's ends), so a stage reads rows the one before has just written, in cache,
    instead of whole arrays. ``exposure_sum``: the window sums of ``e`` (the pattern's, cached), or empty to
    compute them (of the uncensored exposures) in the pass.
    Out: ``w``; ``wn`` (``w`` itself unless ``flagged``); x = s / e into ``x``: (H, W) where ``flagged`` (the
    censored step reads it; then x, w and wn are set on every row), else a ring of the window's height; in rows
    [first, last) the result (``image``), L^ (``estimate``), its information (``total``), the wide fallback's
    ``candidates`` and 1 / total in ``variance`` unless it is empty; exposure sum <= 0 (``lower``) where w
    is set, False elsewhere. Returns (the candidates' count, whether any pixel is ``lower``): the caller
    fills the lower bounds.

    ``window``: (2, H, W) float32, or of no rows: also the motion tests' window mean and its variance in rows
    [first, last) (base.window_level_row; the window sums of the uncensored readings are the pilot's, and
    those of G^2 e and G^2 two more row and column filters), with ``window_noise`` (1 / g, sigma^2) of the
    sensor; 0 and an infinite variance where the window holds no uncensored reading."""
    h, width = s.shape
    ry = ky.size // 2
    windowed = window.shape[1] > 0
    ky2, kx2 = ky * ky, kx * kx
    given = exposure_sum.size > 0
    depth = min(h, 2 * ry + 1)  # a window's rows, reflected at the ends, lie among the last `depth` computed
    square_rows = np.empty((2, depth if windowed else 0, width), np.float32)  # row sums of G^2 e and of G^2
    square_sums = np.empty((2, width if windowed else 0), np.float32)
    signal_rows, exposure_rows = np.empty((depth, width), np.float32), np.empty((depth, width), np.float32)
    lowest_rows = np.empty((depth if flagged else 0, width), np.float32)
    weight_rows, weighted_rows = np.empty((depth, width), np.float32), np.empty((depth, width), np.float32)
    excess_rows, q_rows = np.empty((depth, width), np.float32), np.empty((depth, width), np.float32)
    neighbours = np.empty((ry + 1, width), np.float32)  # m from step 2 until step 3 reads it, ry rows later
    sums, exposure_row, lowest, a, b = (np.empty(width, np.float32), np.empty(width, np.float32),
                                        np.empty(width, np.float32), np.empty(width, np.float32),
                                        np.empty(width, np.float32))
    low, everywhere = np.empty(width, np.bool_), np.empty(width, np.bool_)
    index, packed = np.empty(width, np.int64), np.empty((3, width), np.float32)  # _blend's scratch
    at_bottom = np.zeros(h, np.int64)
    if windowed and not flagged:  # every reading kept: each row's sums of G^2 are the same, made once
        b[:] = np.float32(1.0)
        for slot in range(depth):
            _row_filter(b, kx2, square_rows[1, slot])
    rows = np.empty(ky.size, np.int64)
    # rows each stage computes: those the next one's windows read (with the censored step, step 1 everywhere)
    first1, last1 = (0, h) if flagged else (max(first - 2 * ry, 0), min(last + 2 * ry, h))
    first0, last0 = max(first1 - ry, 0), min(last1 + ry, h)
    first2, last2 = max(first - ry, 0), min(last + ry, h)
    lower[:first1] = False
    lower[last1:] = False
    count, lowered = 0, False
    for i in range(h + 3 * ry):
        r = i
        if first0 <= r < last0:  # row filters of the readings and exposures (uncensored ones)
            if flagged:
                _uncensored(s[r], censored[r], a)
                _row_filter(a, kx, signal_rows[r % depth])
                _uncensored(e[r], censored[r], a)
                _row_filter(a, kx, exposure_rows[r % depth])
                if windowed:
                    _row_filter(a, kx2, square_rows[0, r % depth])
                    _kept(censored[r], b)
                    _row_filter(b, kx2, square_rows[1, r % depth])
                _row_least(e[r], censored[r], kx.size // 2, a, lowest_rows[r % depth])
            else:
                _row_filter(s[r], kx, signal_rows[r % depth])
                if not given:
                    _row_filter(e[r], kx, exposure_rows[r % depth])
                if windowed:  # (the row sums of G^2 over the kept readings are the constant ones below)
                    _row_filter(e[r], kx2, square_rows[0, r % depth])
            at_bottom[r] = _count_at_most(s[r], bottom)
        r = i - ry
        if first1 <= r < last1:  # step 1: w (wn), and the row filters of wn and wn x
            _window_rows(r, h, depth, rows)
            _column_filter(signal_rows, rows, ky, sums)
            if given:
                exposure_row[:] = exposure_sum[r]
            else:
                _column_filter(exposure_rows, rows, ky, exposure_row)
            if flagged:
                rows_min(lowest_rows, rows, lowest)
                _weights_censored(sums, exposure_row, s[r], e[r], censored[r], lowest, w[r], x[r], wn[r], a,
                                  gain_inv, floor, centre)
            else:
                _weights(sums, exposure_row, s[r], e[r], w[r], x[r % x.shape[0]], a, gain_inv, floor, centre)
            lowered |= _at_most_zero(exposure_row, lower[r])
            if windowed and first <= r < last:  # the motion tests' window mean, from the same sums
                _column_filter(square_rows[0], rows, ky2, square_sums[0])
                _column_filter(square_rows[1], rows, ky2, square_sums[1])
                window_level_row(sums, exposure_row, square_sums[0], square_sums[1], window_noise[0],
                                 window_noise[1], window[0, r], window[1, r])
            _row_filter(wn[r], kx, weight_rows[r % depth])
            _row_filter(a, kx, weighted_rows[r % depth])
        r = i - 2 * ry
        if first2 <= r < last2:  # step 2: m and v_m (into `estimate` until step 3), the row filters of b^2's terms
            _window_rows(r, h, depth, rows)
            m = neighbours[r % (ry + 1)]
            _column_filter(weight_rows, rows, ky, estimate[r])
            _column_filter(weighted_rows, rows, ky, m)
            _residuals(estimate[r], m, wn[r], w[r], x[r % x.shape[0]], a, b, centre, kernel_square)
            _row_filter(a, kx, excess_rows[r % depth])
            _row_filter(b, kx, q_rows[r % depth])
        r = i - 3 * ry
        if first <= r < last:  # steps 3 and 4, 0 at the bottom of the raw range, the wide fallback's candidates
            _window_rows(r, h, depth, rows)
            _column_filter(excess_rows, rows, ky, image[r])
            _column_filter(q_rows, rows, ky, total[r])
            _blend(image[r], total[r], estimate[r], neighbours[r % (ry + 1)], w[r], x[r % x.shape[0]], threshold,
                   coefficients, index, packed)
            _zero_bottom_row(s, at_bottom, r, bottom, ry, kx.size // 2, low, everywhere, image[r])
            if variance.size > 0:
                _reciprocal(total[r], variance[r])
            count += _candidates(estimate[r], total[r], image[r], censored[r], lower[r], candidates[r], z2)
    return count, lowered


@kernel
def _uncensored(values, censored, out):
    """out = values, 0 where censored."""
    for c in range(out.size):
        out[c] = np.float32(0.0) if censored[c] else values[c]


@kernel
def _kept(censored, out):
    """out = 1 where uncensored, 0 where censored."""
    for c in range(out.size):
        out[c] = np.float32(0.0) if censored[c] else np.float32(1.0)


@kernel
def _row_least(e, censored, rx, scratch, out):
    """out = the least exposure of the censored readings within ``rx`` of each pixel of a row (BIG where none),
    borders reflect-101; the middle as vectorised loops (``scratch``: a row)."""
    n, big = e.size, np.float32(BIG)
    for c in range(n):
        scratch[c] = e[c] if censored[c] else big
    ends = min(rx, n)  # the row's ends, whose windows reflect: [0, ends) and [max(n - rx, ends), n)
    for i in range(ends + n - max(n - rx, ends)):
        c = i if i < ends else max(n - rx, ends) + i - ends
        least = big
        for dx in range(-rx, rx + 1):
            least = min(least, scratch[reflect_101(c + dx, n)])
        out[c] = least
    inner = n - 2 * rx
    if inner <= 0:
        return
    middle = out[rx:rx + inner]
    middle[:] = scratch[:inner]
    for dx in range(1, 2 * rx + 1):
        shifted = scratch[dx:dx + inner]
        for i in range(inner):
            middle[i] = min(middle[i], shifted[i])


@kernel
def _window_rows(r, h, depth, rows):
    """rows = the ring slots (row modulo ``depth``) of the window's rows around row ``r`` of ``h``, reflect-101."""
    ry = rows.size // 2
    for dy in range(rows.size):
        rows[dy] = reflect_101(r + dy - ry, h) % depth


@kernel
def _row_filter(source, k, out):
    """out = the symmetric filter ``k`` (odd taps) along one row, borders reflect-101, with ``smooth``'s
    arithmetic: the centre tap, then the pairs of mirrored taps outwards; the middle as vectorised loops."""
    n, rk = source.size, k.size // 2
    ends = min(rk, n)  # the row's ends, whose windows reflect: [0, ends) and [max(n - rk, ends), n)
    for i in range(ends + n - max(n - rk, ends)):
        c = i if i < ends else max(n - rk, ends) + i - ends
        acc = k[rk] * source[c]
        for d in range(1, rk + 1):
            acc += k[rk - d] * (source[reflect_101(c - d, n)] + source[reflect_101(c + d, n)])
        out[c] = acc
    inner = n - 2 * rk
    if inner <= 0:
        return
    middle = out[rk:rk + inner]
    if rk == 1:
        k0, k1 = k[0], k[1]
        left, centre, right = source[:inner], source[1:1 + inner], source[2:2 + inner]
        for i in range(inner):
            middle[i] = k1 * centre[i] + k0 * (left[i] + right[i])
        return
    centre, kc = source[rk:rk + inner], k[rk]
    for i in range(inner):
        middle[i] = kc * centre[i]
    for d in range(1, rk + 1):
        left, right, kd = source[rk - d:rk - d + inner], source[rk + d:rk + d + inner], k[rk - d]
        for i in range(inner):
            middle[i] += kd * (left[i] + right[i])


@kernel
def _column_filter(values, rows, k, out):
    """out = the symmetric filter ``k`` down ``values``' rows ``rows`` (the window's, top to bottom) with
    ``smooth``'s arithmetic: the centre tap, then the pairs outwards (:func:`_column_sums` for 3 or 5 taps)."""
    if k.size == 3 or k.size == 5:
        _column_sums(values, rows, k, out)
        return
    rk = k.size // 2
    centre, kc = values[rows[rk]], k[rk]
    for i in range(out.size):
        out[i] = kc * centre[i]
    for d in range(1, rk + 1):
        above, below, kd = values[rows[rk - d]], values[rows[rk + d]], k[rk - d]
        for i in range(out.size):
            out[i] += kd * (above[i] + below[i])


@kernel
def _count_at_most(values, level):
    """How many of ``values`` are <= ``level``."""
    n = 0
    for c in range(values.size):
        n += values[c] <= level
    return n


@kernel
def _at_most_zero(values, out):
    """out = values <= 0; whether any is."""
    n = 0
    for c in range(values.size):
        out[c] = values[c] <= np.float32(0.0)
    for c in range(values.size):  # counted apart, so that the loop above vectorises
        n += out[c]
    return n > 0


@kernel
def _reciprocal(a, out):
    """out = 1 / a."""
    for c in range(out.size):
        out[c] = np.float32(1.0) / a[c]


@kernel
def _candidates(estimate, information, image, censored, lower, out, z2):
    """out = the pixels whose result cannot tell the level from 0 (L^ <= 0 or L^^2 information < z2), neither
    censored nor a lower bound nor set to 0 at the bottom of the raw range; flat arrays; their count."""
    zero = np.float32(0.0)
    for k in range(out.size):
        e = estimate[k]
        out[k] = ((e <= zero) | (e * e * information[k] < z2)) & (image[k] > zero) & ~censored[k] & ~lower[k]
    n = 0  # counted apart: a count inside the loop above keeps LLVM from vectorising it
    for k in range(out.size):
        n += out[k]
    return n


def _wide_reach(ky: np.ndarray, kx: np.ndarray) -> tuple[int, int]:
    """(rows, columns) the wide fallback reads beyond a pixel: the widest scale's blocks, one block away, and half
    a block beyond their centres."""
    by, bx = len(ky) * 3 ** max(WIDE_SCALES - 1, 0), len(kx) * 3 ** max(WIDE_SCALES - 1, 0)
    return by + by // 2, bx + bx // 2


def _wide_fallback(inp: SveInput, spans: list[tuple[int, int, int, int]], darks: list[_Dark], image: np.ndarray,
                   variance: np.ndarray | None, ky: np.ndarray, kx: np.ndarray, workers: int | Executor) -> None:
    """Where a pixel's result cannot tell its level from 0, the levels of wider windows that are flat within their
    noise, scale by scale; ``image`` (and ``variance``) in place, float32 (H, W).

    A 3x3 window cannot tell a level far below its noise from 0, and step 4's
    answer there (about half the estimate's deviation) lies far above a level
    many stops lower. At scale j the eight blocks of (window x 3^j) around the
    pixel, one block away (so they hold none of the readings of its current
    estimate), give a neighbour level m = sum X_b / sum W_b (W_b, X_b: the
    block's sums of w and w x, the weights of step 1) with variance
    1 / sum W_b, if the region is flat. Whether it is, is the blocks' own
    evidence: under a constant level chi2 = sum W_b (X_b / W_b - m)^2 is
    chi-square with (blocks - 1) degrees of freedom; its excess over that,
    shrunk by CONTRAST_SIGMA of its standard errors (sqrt(2 dof)), over
    sum W_b is the squared bias b^2 of m, as step 2's is of the window's
    (bright structure a block away makes it large, and m counts for little).
    The pixel's estimate and m are then blended as in step 3 (information
    adds: t + 1 / (1 / sum W_b + b^2)), and the next scale (blocks three times
    larger around the blocks used) follows only where the blend still cannot
    tell the level from 0 and the blocks showed no structure (b^2 = 0). A block
    holding a censored reading (a level at least its bound, far above) stops
    the pixel at the scale before, as does a frame too small for the scale's
    blocks. Readings at the raw range's bottom count as what they read, as in
    steps 1-3. Step 4 is then applied to the new estimate.

    Cost: only strips holding such pixels, over their rows and as far as the
    widest blocks reach. Where they are many, each scale's block sums are two
    box filters over those rows; where few (fewer than one in WIDE_DIRECT times
    a block's pixels), each pixel sums its blocks' readings itself.
    """
    h, width = inp.shape
    reach = _wide_reach(ky, kx)
    none = np.empty((0, 0), np.float32)

    def band(group: range) -> None:
        members = [i for i in group if darks[i].count]
        if not members:
            return
        top, end = spans[members[0]][1], spans[members[-1]][2]
        r0, r1 = max(top - reach[0], 0), min(end + reach[0], h)
        weights = _joined([d.weights[max(r0 - t, 0):max(min(r1, e) - t, 0)]
                           for (_, t, e, _), d in zip(spans, darks) if t < r1 and e > r0])
        signal, exposure, censored = inp.signal[r0:r1], inp.exposure[r0:r1], inp.censored[r0:r1]
        active = {i: darks[i].candidates.copy() for i in members}
        changed = {i: np.zeros_like(active[i]) for i in members}
        count, by, bx = sum(darks[i].count for i in members), len(ky), len(kx)
        weighted = None
        for _ in range(WIDE_SCALES):
            if 3 * by > h or 3 * bx > width:
                break
            boxes = count * by * bx * WIDE_DIRECT > weights.size  # many: box filters over the rows
            if boxes:
                if weighted is None:
                    weighted = np.empty_like(weights)
                    flagged = _wide_prepare(*flat(weights, signal, exposure, censored, weighted))
                box_w, means = _box(weights, by, bx), _box(weighted, by, bx)
                held = _held(censored, by, bx) if flagged else censored  # unused when none is censored
                _block_means(*flat(box_w, means, held), flagged)
            count = 0
            for i in members:
                d, offset = darks[i], spans[i][1] - r0
                count += (_wide_boxes(box_w, means, offset, by, bx, active[i], changed[i], d.estimate,
                                      d.information) if boxes else
                          _wide_direct(weights, signal, exposure, censored, offset, by, bx, active[i], changed[i],
                                       d.estimate, d.information))
            if count == 0:
                break
            by, bx = 3 * by, 3 * bx
        for i in members:
            rows = slice(*spans[i][1:3])
            _posterior_at(changed[i], darks[i].estimate, darks[i].information, image[rows], posterior_polynomial(),
                          none if variance is None else variance[rows])

    groups = [range(i, min(i + WIDE_GROUP, len(spans))) for i in range(0, len(spans), WIDE_GROUP)]
    map_on(workers, band, groups)


def _box(a: np.ndarray, by: int, bx: int) -> np.ndarray:
    """Sums of ``a`` (float32 (H, W)) over the by x bx box around each pixel, borders reflect-101."""
    return cv2.boxFilter(a, cv2.CV_32F, (bx, by), normalize=False, borderType=cv2.BORDER_REFLECT_101)


def _held(censored: np.ndarray, by: int, bx: int) -> np.ndarray:
    """Where the by x bx box around a pixel holds a censored reading: bool (H, W) of ``censored`` (bool (H, W)),
    borders reflect-101 (the boxes of :func:`_box`)."""
    return cv2.dilate(censored.view(np.uint8), np.ones((by, bx), np.uint8),
                      borderType=cv2.BORDER_REFLECT_101).view(bool)


@kernel
def _wide_prepare(weights, signal, exposure, censored, weighted):
    """weighted = w x (x = s / e); flat arrays; whether any reading is censored."""
    for k in range(weights.size):
        weighted[k] = weights[k] * (signal[k] / exposure[k])
    flagged = 0  # counted apart: a count inside the loop above keeps LLVM from vectorising it
    for k in range(censored.size):
        flagged += censored[k]
    return flagged > 0


@kernel
def _block_means(box_w, box_wx, held, flagged):
    """box_wx = the blocks' levels X / W (0 where a block holds no reading: W <= TINY), NaN where a block holds a
    censored reading (``held``, if ``flagged``); flat arrays, in place."""
    tiny, nan = np.float32(TINY), np.float32(np.nan)
    for k in range(box_w.size):
        w = box_w[k]
        level = box_wx[k] / max(w, tiny) if w > tiny else np.float32(0.0)
        box_wx[k] = nan if flagged and held[k] else level


@kernel
def _block(w, level):
    """A block's (W, W m, 1) where it holds readings (W > TINY), else zeros; float32."""
    zero, one = np.float32(0.0), np.float32(1.0)
    valid = w > np.float32(TINY)
    return (w if valid else zero), (w * level if valid else zero), (one if valid else zero)


@kernel
def _deviation(w, level, mean):
    """W (m - mean)^2 of a block holding readings, else 0; float32."""
    d = level - mean
    return w * d * d if w > np.float32(TINY) else np.float32(0.0)


@kernel
def _wide_blend(block_w, block_m, r, c, active, changed, estimate, information):
    """The blend of one scale of :func:`_wide_fallback` at pixel (r, c) from its eight blocks (float32 (8,): W and
    the level m = X / W, NaN where flagged); whether the next scale follows. The same arithmetic, in the same order,
    as :func:`_wide_row` (bit for bit)."""
    zero = np.float32(0.0)
    sum_w, sum_wx, blocks, bad = zero, zero, zero, False
    for b in range(8):
        a, x, k = _block(block_w[b], block_m[b])
        sum_w += a
        sum_wx += x
        blocks += k
        bad |= block_m[b] != block_m[b]
    mean = sum_wx / max(sum_w, np.float32(TINY))
    chi2 = zero
    for b in range(8):
        chi2 += _deviation(block_w[b], block_m[b], mean)
    if bad or blocks < np.float32(2.0):
        active[r, c] = False
        return False
    value, t, keep = _wide_step(estimate[r, c], information[r, c], sum_w, mean, chi2, blocks)
    estimate[r, c] = value
    information[r, c] = t
    changed[r, c] = True
    active[r, c] = keep
    return keep


@kernel
def _wide_step(estimate, information, sum_w, level, chi2, blocks):
    """(estimate, information, whether the next scale follows) after blending in a scale's neighbour level
    (:func:`_wide_fallback`), float32."""
    zero, one, two = np.float32(0.0), np.float32(1.0), np.float32(2.0)
    sigmas = np.float32(CONTRAST_SIGMA)
    dof = blocks - one
    bias2 = max(chi2 - dof - sigmas * np.sqrt(two * dof), zero) / sum_w
    weight = one / (one / sum_w + bias2)
    t = information + weight
    value = (estimate * information + level * weight) / t
    keep = (bias2 <= zero) & ((value <= zero) | (value * value * t < sigmas * sigmas))
    return value, t, keep


@kernel
def _wide_boxes(box_w, means, offset, by, bx, active, changed, estimate, information):
    """One scale of :func:`_wide_fallback` at the ``active`` pixels of a strip's rows (bool (R, W); row r of the
    strip is row r + offset of the band's block sums ``box_w`` and levels ``means`` (:func:`_block_means`), blocks
    by x bx); the number of pixels the next scale follows at. A row with many active pixels (more than one in
    DENSE_ROW) is computed whole away from its ends (:func:`_wide_row`, vectorised), others pixel by pixel;
    both alike bit for bit."""
    h, width = box_w.shape
    rows, cols = np.empty(3, np.int64), np.empty(3, np.int64)
    block_w, block_m = np.empty(8, np.float32), np.empty(8, np.float32)
    inner = width - 2 * bx
    kept = 0
    for r in range(active.shape[0]):
        br = r + offset
        n = 0
        for c in range(width):
            n += active[r, c]
        if n == 0:
            continue
        for i in range(3):
            rows[i] = reflect_101(br + (i - 1) * by, h)
        whole = n * DENSE_ROW > width and inner > 0
        if whole:
            kept += _wide_row(box_w, means, rows, bx, active[r, bx:bx + inner], changed[r, bx:bx + inner],
                              estimate[r, bx:bx + inner], information[r, bx:bx + inner])
        for k in range(2 * bx if whole else width):  # a whole row: its ends alone are left
            c = k if k < bx or not whole else k + inner
            if not active[r, c]:
                continue
            for i in range(3):
                cols[i] = reflect_101(c + (i - 1) * bx, width)
            b = 0
            for i in range(3):
                for j in range(3):
                    if i == 1 and j == 1:
                        continue
                    block_w[b], block_m[b] = box_w[rows[i], cols[j]], means[rows[i], cols[j]]
                    b += 1
            kept += _wide_blend(block_w, block_m, r, c, active, changed, estimate, information)
    return kept


@kernel
def _wide_row(box_w, means, rows, bx, active, changed, estimate, information):
    """:func:`_wide_blend` at every pixel of a row away from its ends (columns bx .. W - bx: ``active``,
    ``changed``, ``estimate`` and ``information`` are that part of the row), in one loop over the row that LLVM
    vectorises; the number of pixels kept active."""
    n = active.size
    two = 2 * bx
    r0, r1, r2 = rows[0], rows[1], rows[2]
    w0, w1, w2, w3 = box_w[r0, :n], box_w[r0, bx:bx + n], box_w[r0, two:two + n], box_w[r1, :n]
    w4, w5, w6, w7 = box_w[r1, two:two + n], box_w[r2, :n], box_w[r2, bx:bx + n], box_w[r2, two:two + n]
    m0, m1, m2, m3 = means[r0, :n], means[r0, bx:bx + n], means[r0, two:two + n], means[r1, :n]
    m4, m5, m6, m7 = means[r1, two:two + n], means[r2, :n], means[r2, bx:bx + n], means[r2, two:two + n]
    zero, tiny, two_blocks = np.float32(0.0), np.float32(TINY), np.float32(2.0)
    for c in range(n):
        a0, b0, n0 = _block(w0[c], m0[c])
        a1, b1, n1 = _block(w1[c], m1[c])
        a2, b2, n2 = _block(w2[c], m2[c])
        a3, b3, n3 = _block(w3[c], m3[c])
        a4, b4, n4 = _block(w4[c], m4[c])
        a5, b5, n5 = _block(w5[c], m5[c])
        a6, b6, n6 = _block(w6[c], m6[c])
        a7, b7, n7 = _block(w7[c], m7[c])
        bad = ((m0[c] != m0[c]) | (m1[c] != m1[c]) | (m2[c] != m2[c]) | (m3[c] != m3[c]) | (m4[c] != m4[c])
               | (m5[c] != m5[c]) | (m6[c] != m6[c]) | (m7[c] != m7[c]))
        sum_w = zero + a0 + a1 + a2 + a3 + a4 + a5 + a6 + a7
        sum_wx = zero + b0 + b1 + b2 + b3 + b4 + b5 + b6 + b7
        blocks = zero + n0 + n1 + n2 + n3 + n4 + n5 + n6 + n7
        mean = sum_wx / max(sum_w, tiny)
        chi2 = (zero + _deviation(w0[c], m0[c], mean) + _deviation(w1[c], m1[c], mean)
                + _deviation(w2[c], m2[c], mean) + _deviation(w3[c], m3[c], mean)
                + _deviation(w4[c], m4[c], mean) + _deviation(w5[c], m5[c], mean)
                + _deviation(w6[c], m6[c], mean) + _deviation(w7[c], m7[c], mean))
        go = active[c] & ~bad & (blocks >= two_blocks)
        value, t, keep = _wide_step(estimate[c], information[c], sum_w, mean, chi2, blocks)
        estimate[c] = value if go else estimate[c]
        information[c] = t if go else information[c]
        changed[c] |= go
        active[c] = go & keep
    kept = 0  # counted apart: a count inside the loop above keeps LLVM from vectorising it
    for c in range(n):
        kept += active[c]
    return kept


@kernel
def _wide_direct(weights, signal, exposure, censored, offset, by, bx, active, changed, estimate, information):
    """:func:`_wide_boxes` with each active pixel summing its blocks' readings itself (few active pixels): the
    band's weights, signals, exposures and censoring (row r of ``active`` is row r + offset of them)."""
    h, width = weights.shape
    tiny = np.float32(TINY)
    block_w, block_m = np.empty(8, np.float32), np.empty(8, np.float32)
    kept = 0
    for r in range(active.shape[0]):
        br = r + offset
        for c in range(width):
            if not active[r, c]:
                continue
            for i in range(9):
                if i == 4:
                    continue
                top, left = br + (i // 3 - 1) * by - by // 2, c + (i % 3 - 1) * bx - bx // 2
                wb, xb, bad = 0.0, 0.0, False
                for dy in range(by):
                    rr = reflect_101(top + dy, h)
                    for dx in range(bx):
                        cc = reflect_101(left + dx, width)
                        bad |= censored[rr, cc]
                        w = weights[rr, cc]
                        wb += w
                        xb += w * (signal[rr, cc] / exposure[rr, cc])
                b = i if i < 4 else i - 1
                w32 = np.float32(wb)
                block_w[b] = w32
                block_m[b] = np.float32(np.nan) if bad else (np.float32(xb) / max(w32, tiny) if w32 > tiny
                                                             else np.float32(0.0))
            kept += _wide_blend(block_w, block_m, r, c, active, changed, estimate, information)
    return kept


@kernel
def _posterior_at(changed, estimate, information, image, coefficients, variance):
    """image = step 4's result of (estimate, information) at the ``changed`` pixels of (R, W) arrays, variance =
    1 / information there unless ``variance`` is empty. Row by row: a row with many (one in FEW_NEAR_ZERO or more)
    through :func:`_nonnegative` whole, then chosen; a row with few packed into short arrays first."""
    width = changed.shape[1]
    out, packed_image = np.empty(width, np.float32), np.empty(width, np.float32)
    packed_estimate, packed_information = np.empty(width, np.float32), np.empty(width, np.float32)
    index = np.empty(width, np.int64)
    one = np.float32(1.0)
    for r in range(changed.shape[0]):
        row = changed[r]
        n = 0
        for c in range(width):
            n += row[c]
        if n == 0:
            continue
        if n * FEW_NEAR_ZERO >= width:
            out[:] = estimate[r]
            _nonnegative(out, estimate[r], information[r], coefficients)
            target = image[r]
            for c in range(width):
                target[c] = out[c] if row[c] else target[c]
        else:
            n = 0
            for c in range(width):
                if row[c]:
                    index[n] = c
                    packed_estimate[n], packed_information[n] = estimate[r, c], information[r, c]
                    n += 1
            packed_image[:n] = packed_estimate[:n]
            _nonnegative(packed_image[:n], packed_estimate[:n], packed_information[:n], coefficients)
            for j in range(n):
                image[r, index[j]] = packed_image[j]
        if variance.size > 0:
            for c in range(width):
                variance[r, c] = one / information[r, c] if row[c] else variance[r, c]


@kernel
def _zero_bottom_row(s, at_bottom, r, bottom, ry, rx, low, everywhere, out):
    """out = 0, in place, where every reading of the pixel's window (2 ry + 1 rows, 2 rx + 1 columns, borders
    reflect-101) lies at the bottom of the raw range (raw 0, a signal of ``bottom`` = -black): clipped there,
    such readings say only "at most", as saturated ones say "at least", and their tightest answer is 0 (a black
    frame stays black; :func:`_nonnegative` would lift it). Row ``r`` of (H, W) ``s``, ``out`` its row of the
    image; tested only if every row of its window holds a reading at the bottom (``at_bottom``: their counts
    per row): the window's rows, then its columns, as vectorised loops (``low`` and ``everywhere``: scratch
    rows)."""
    h, width = s.shape
    for dy in range(2 * ry + 1):
        if at_bottom[reflect_101(r + dy - ry, h)] == 0:
            return
    low[:] = True
    for dy in range(2 * ry + 1):
        row = s[reflect_101(r + dy - ry, h)]
        for c in range(width):
            low[c] &= row[c] <= bottom
    ends = min(rx, width)  # the row's ends, whose windows reflect: [0, ends) and [max(width - rx, ends), width)
    for i in range(ends + width - max(width - rx, ends)):
        c = i if i < ends else max(width - rx, ends) + i - ends
        everywhere[c] = True
        for dx in range(2 * rx + 1):
            everywhere[c] &= low[reflect_101(c + dx - rx, width)]
    inner = width - 2 * rx
    if inner > 0:
        middle = everywhere[rx:rx + inner]
        middle[:] = True
        for dx in range(2 * rx + 1):
            shifted = low[dx:dx + inner]
            for i in range(inner):
                middle[i] &= shifted[i]
    for c in range(width):
        out[c] = np.float32(0.0) if everywhere[c] else out[c]


@lru_cache(maxsize=16)
def _exposure_sum(pattern: Pattern, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Window sum of the exposure map and the map's first tile; float32; read-only.

    Strips start on whole tiles, so every strip of one height shares them
    (the first tile tells a caller whether its exposures have that phase).
    """
    ky, kx = kernels(pattern.shape)
    exposure = pattern.exposure_map(shape)
    exposure_sum = smooth(exposure, ky, kx)
    first_tile = exposure[:pattern.shape[0], :pattern.shape[1]].copy()
    for array in (exposure_sum, first_tile):
        array.setflags(write=False)
    return exposure_sum, first_tile


@kernel
def _inverse_variance(signal_sum, exposure_sum, s_valid, e, e_valid, gain_inv, floor, centre):
    """w = e e_valid / (e L0 / g + sigma^2) at the pilot L0 = max(sum s / sum e, 0) of the window *without the pixel*
    (its own reading would make its weight fall as it reads high: a bias low); 0 where e_valid = 0."""
    rest = max(exposure_sum - centre * e_valid, np.float32(TINY))
    pilot = max((signal_sum - centre * s_valid) / rest, np.float32(0.0))
    return e * e_valid / (pilot * e * gain_inv + floor)


@kernel
def _weights(signal_sum, exposure_sum, s, e, w, x, wx, gain_inv, floor, centre):
    """Frame without censored pixels: w of every reading, x = s / e, and w x."""
    for k in range(w.size):
        wk = _inverse_variance(signal_sum[k], exposure_sum[k], s[k], e[k], e[k], gain_inv, floor, centre)
        xk = s[k] / e[k]
        w[k] = wk
        x[k] = xk
        wx[k] = wk * xk


@kernel
def _weights_censored(signal_sum, exposure_sum, s, e, censored, lowest, w, x, wn, wx, gain_inv, floor, centre):
    """w (0 at censored pixels), x = s / e; wn = w but 0 next to a censored pixel of lower or equal exposure; wn x."""
    zero = np.float32(0.0)
    for k in range(w.size):
        c = censored[k]
        wk = _inverse_variance(signal_sum[k], exposure_sum[k], zero if c else s[k], e[k], zero if c else e[k],
                               gain_inv, floor, centre)
        xk = s[k] / e[k]
        w[k] = wk
        x[k] = xk
        wnk = zero if lowest[k] <= e[k] else wk
        wn[k] = wnk
        wx[k] = wnk * xk


@kernel
def _residuals(var_m, m, wn, w, x, excess_q, q, centre, kernel_square):
    """Neighbour estimate and the terms of b^2, with v_r = v_p + v_m: q = 1 / v_r^2, excess_q = q ((x - m)^2 - v_r).

    ``var_m`` and ``m`` come in holding the window sums of wn and wn x, and
    leave holding v_m and m (the sums without the centre pixel).
    """
    one, tiny = np.float32(1.0), np.float32(TINY)
    for k in range(w.size):
        sum_w = max(var_m[k] - centre * wn[k], tiny)  # no neighbours: m = 0 with a huge variance
        mk = (m[k] - centre * (wn[k] * x[k])) / sum_w
        var_mk = kernel_square / sum_w
        var_r = one / max(w[k], tiny) + var_mk  # censored: v_p ~ 1 / tiny, so no evidence
        d = x[k] - mk
        qk = one / (var_r * var_r)
        m[k] = mk
        var_m[k] = var_mk
        excess_q[k] = (d * d - var_r) * qk
        q[k] = qk


@kernel
def _blend(image, total, var_m, m, w, x, threshold, coefficients, index, packed):
    """The result: exp(E[log L]) of L ~ N(L^, 1 / total) restricted to L >= 0 (:func:`_nonnegative`), with
    L^ = m + (x - m) w / total, total = w + 1 / (b^2 + v_m), b^2 = max(B - threshold SE, 0).

    B = sum excess_q / sum q is the window's estimate of the squared bias, SE its
    standard error under a flat scene, sqrt(2 kernel_square / sum q) (each
    residual's squared excess has variance 2 v_r^2 = 2 / q). ``threshold``:
    CONTRAST_SIGMA^2 * 2 kernel_square, so b^2 = max(B - sqrt(threshold / sum q), 0).
    ``image`` and ``total`` come in holding the window sums of excess_q and q; ``var_m`` leaves holding L^.
    ``index`` (int64) and ``packed`` (float32 (3, N)): scratch of at least the arrays' size N.
    """
    zero, one, tiny = np.float32(0.0), np.float32(1.0), np.float32(TINY)
    high = np.float32(POSTERIOR_HIGH * POSTERIOR_HIGH)
    dark = 0
    for k in range(w.size):  # a loop without branches, which LLVM vectorises
        weight = max(total[k], tiny)
        excess = max(image[k] / weight - np.sqrt(threshold / weight), zero) + var_m[k]
        t = one / excess + w[k]
        estimate = m[k] + (x[k] - m[k]) * (w[k] / t)
        image[k] = estimate
        var_m[k] = estimate  # kept for the pixels near 0, below
        total[k] = t
        dark += (estimate <= zero) | (estimate * estimate * t < high)
    if dark == 0:
        return
    if dark * FEW_NEAR_ZERO >= w.size:
        _nonnegative(image, var_m, total, coefficients)
        return
    # Few pixels near 0 (a bright scene): packed into short arrays, the same pass on them alone.
    n = _near_zero(var_m, total, index)
    near_image, near_estimate, near_information = packed[0, :n], packed[1, :n], packed[2, :n]
    for j in range(n):
        k = index[j]
        near_image[j], near_estimate[j], near_information[j] = image[k], var_m[k], total[k]
    _nonnegative(near_image, near_estimate, near_information, coefficients)
    for j in range(n):
        image[index[j]] = near_image[j]


#: :func:`_blend` runs :func:`_nonnegative` on the pixels near 0 alone when fewer than one in this many are.
FEW_NEAR_ZERO = 4
#: Margin of :func:`_near_zero`'s test over :func:`_nonnegative`'s own: z = L^ sqrt(information) < POSTERIOR_HIGH,
#: rounded to float32, implies L^^2 information < POSTERIOR_HIGH^2 (1 + 1e-6) rounded, so this margin misses none.
NEAR_MARGIN = 1.0 + 1e-5


@kernel
def _near_zero(estimate, information, index):
    """The indices of the flat arrays' pixels that :func:`_nonnegative` may change (L^ <= 0 or within a little
    more than POSTERIOR_HIGH deviations of 0), packed into the front of ``index``; their count. Without branches."""
    zero, loose = np.float32(0.0), np.float32(POSTERIOR_HIGH * POSTERIOR_HIGH * NEAR_MARGIN)
    n = 0
    for k in range(estimate.size):
        e = estimate[k]
        index[n] = k
        n += (e <= zero) | (e * e * information[k] < loose)
    return n


#: The range of z = estimate / sigma over which :func:`posterior_table` tabulates, and its step. From
#: POSTERIOR_HIGH up the result is the estimate itself: exp(E[log L]) is below it by 1/(2 z^2), under 0.08 %.
POSTERIOR_LOW, POSTERIOR_HIGH, POSTERIOR_STEP = -30.0, 25.0, 1.0 / 16
#: Degree of the polynomial :func:`posterior_polynomial` fits (5e-4 relative error at most, float32); the kernel
#: (:func:`_nonnegative`) writes out its Horner scheme for this degree.
POSTERIOR_DEGREE = 16
EULER_GAMMA = 0.5772156649015329
#: exp(-Euler's gamma): exp(E[log L]) of an exponential distribution of mean 1.
TAIL = math.exp(-EULER_GAMMA)


@lru_cache(maxsize=1)
def posterior_table() -> np.ndarray:
    """g(z) = exp(E[log L]) for L ~ N(z, 1) restricted to L > 0, at z = POSTERIOR_LOW + i POSTERIOR_STEP up to
    POSTERIOR_HIGH; float64, read-only. Integrated over u = log L (the integrand is smooth there)."""
    z = np.arange(POSTERIOR_LOW, POSTERIOR_HIGH + POSTERIOR_STEP / 2, POSTERIOR_STEP)[:, None]
    u = np.linspace(-50.0, np.log(POSTERIOR_HIGH + 14.0), 12000)[None, :]
    level = np.exp(u)
    # phi(L - z) dL, times phi(0) / phi(z) below 0 (no underflow there; the scale cancels)
    density = np.exp(-0.5 * (level - z) ** 2 + 0.5 * np.minimum(z, 0) ** 2 + u)
    table = np.exp((u * density).sum(axis=1) / density.sum(axis=1))
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
def _nonnegative(image, estimate, information, coefficients):
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
    zero, half, tiny = np.float32(0.0), np.float32(0.5), np.float32(TINY)
    high, c4 = np.float32(POSTERIOR_HIGH), np.float32(4.0 * TAIL)
    # Horner's scheme written out (a loop over the coefficients would not vectorise): degree POSTERIOR_DEGREE = 16
    p0, p1, p2, p3, p4, p5, p6, p7, p8 = (coefficients[0], coefficients[1], coefficients[2], coefficients[3],
                                          coefficients[4], coefficients[5], coefficients[6], coefficients[7],
                                          coefficients[8])
    p9, p10, p11, p12, p13, p14, p15, p16 = (coefficients[9], coefficients[10], coefficients[11], coefficients[12],
                                             coefficients[13], coefficients[14], coefficients[15], coefficients[16])
    for k in range(image.size):
        root_t = np.sqrt(max(information[k], tiny))
        z = estimate[k] * root_t
        r = np.sqrt(z * z + c4)
        base = (z + r) * half if z > zero else c4 * half / (r - z)
        u = z / r
        p = (((((((((((((((p16 * u + p15) * u + p14) * u + p13) * u + p12) * u + p11) * u + p10) * u + p9) * u
                      + p8) * u + p7) * u + p6) * u + p5) * u + p4) * u + p3) * u + p2) * u + p1) * u + p0
        image[k] = base * p / root_t if z < high else image[k]


def _censored_pixels(inp: SveInput, image: np.ndarray, w: np.ndarray, x: np.ndarray, ky: np.ndarray,
                     kx: np.ndarray) -> np.ndarray:
    """Set ``image`` at censored pixels, in place; returns the pixels left as bounds only, bool (H, W).

    A censored pixel takes the plain (equal-weight) window mean of the
    uncensored neighbours consistent with its bound (x_i + 2 sigma_i >= bound),
    and at least the bound. Equal weights, because noise weights at each
    neighbour's own radiance favour the darker neighbours, and next to a
    censored pixel the surviving ones are the darker ones. With no consistent
    neighbour the pixel is returned for the caller to give it the largest bound
    of its window.

    Three ways to the same sums. A folded input (SveInput.folded: a colour frame's
    luminance, whose exposures vary off the levels), and a tile whose window has
    at most DIRECT_TAPS taps, visit each censored pixel's window once, testing
    its neighbours against its own bound censor / e (:func:`_censored_each`):
    the cost follows the number of censored pixels. A 5x3 window computes, at
    each censored pixel, the window sums of its own level's consistent readings
    with OpenCV's arithmetic (:func:`_censored_separable`): the same values as
    the per-level sums below, at a cost that follows the rows holding censored
    pixels. Otherwise (longer windows, and calibrated per-pixel exposure maps,
    tested against the bound of their nominal level) each level with censored
    pixels gets two window sums over the box around them, one window radius
    wider (cut at the frame's edges), so that inside it they equal whole-frame
    sums: the cost follows the levels' boxes.
    """
    f32 = np.float32
    censor = inp.sensor.censor_level
    if inp.folded or (inp.pattern.pixel_map is None and ky.size * kx.size <= DIRECT_TAPS):
        bound_only = np.zeros(inp.shape, bool)
        _censored_each(inp.censored, inp.exposure, w, x, image, bound_only, ky, kx, f32(censor))
        return bound_only
    if inp.pattern.pixel_map is None and kx.size == 3 and ky.size == 5:  # OpenCV's sums, computed per pixel
        bound_only = np.zeros(inp.shape, bool)
        _censored_separable(inp.censored, inp.exposure, w, x, image, bound_only, ky, kx,
                            *_level_bounds_of(inp.pattern, censor))
        return bound_only
    levels = inp.pattern.levels.tolist()
    if inp.pattern.pixel_map is None:
        key, values = inp.exposure, np.array(levels, f32)
    else:
        key, values = inp.pattern.level_index_map(inp.shape), np.arange(len(levels), dtype=np.uint8)
    h, width = inp.shape
    ry, rx = len(ky) // 2, len(kx) // 2
    boxes = np.empty((len(levels), 4), np.int64)  # first row, last row, first column, last column
    if len(levels) < 64:
        _level_boxes(*flat(inp.censored, key), values, width, boxes)
    else:  # more levels than bits in a mask: every level's box is the whole frame
        boxes[:] = (0, h - 1, 0, width - 1)
    bound_only = np.zeros(inp.shape, bool)
    for level, value, (top, bottom, left, right) in zip(levels, values, boxes.tolist()):
        if bottom < 0:
            continue  # no censored pixel of this level
        r0, r1, c0, c1 = max(top - ry, 0), min(bottom + ry + 1, h), max(left - rx, 0), min(right + rx + 1, width)
        consistent, consistent_x = np.empty((r1 - r0, c1 - c0), f32), np.empty((r1 - r0, c1 - c0), f32)
        _consistent(*flat(w, x, consistent, consistent_x), width, r0, c0, c1 - c0, f32(censor / level))
        count, sum_x = smooth(consistent, ky, kx), smooth(consistent_x, ky, kx)
        _fill_censored(*flat(inp.censored, key, x, image, bound_only, count, sum_x), width, value, r0, c0, c1 - c0,
                       top, bottom + 1, left, right + 1)
    return bound_only


@lru_cache(maxsize=16)
def _level_bounds_of(pattern: Pattern, censor: float) -> tuple[np.ndarray, np.ndarray]:
    """The pattern's levels and the bound a censored reading at each implies (censor / level, rounded as the
    per-level sums of :func:`_censored_pixels` round it); float32 (K,), read-only."""
    levels = pattern.levels.tolist()
    values, bounds = np.array(levels, np.float32), np.array([censor / level for level in levels], np.float32)
    values.setflags(write=False)
    bounds.setflags(write=False)
    return values, bounds


@kernel
def _censored_each(censored, exposure, w, x, image, bound_only, ky, kx, censor):
    """At each censored pixel p of (H, W) arrays: image = max(window mean (binomial weights, borders reflect-101
    as the window sums elsewhere) of the readings consistent with p's own bound censor / e_p, x_p); ``bound_only``
    where none is. Consistent (:func:`_consistent_row`): w > 0 and x + 2 / sqrt(w) >= bound, tested squared.

    Its cost follows the number of censored pixels, not the levels they are at: a row with few of them visits
    each one's window (:func:`_censored_pixel`); a row with many (more than one in DENSE_ROW) sums every
    pixel's window at once, a loop over the row per tap (:func:`_censored_row`), which LLVM vectorises. Both add
    the same terms in the same order.
    """
    h, width = censored.shape
    ry, rx = ky.size // 2, kx.size // 2
    rows = np.empty(ky.size, np.int64)
    cols = np.empty(kx.size, np.int64)
    count, total, bound = np.empty(width, np.float32), np.empty(width, np.float32), np.empty(width, np.float32)
    for r in range(h):
        n = 0
        for c in range(width):
            n += censored[r, c]
        if n == 0:
            continue
        for dy in range(ky.size):
            rows[dy] = reflect_101(r + dy - ry, h)
        if n * DENSE_ROW > width and width > 2 * rx:
            _censored_row(exposure[r], w, x, rows, ky, kx, censor, count, total, bound)
            for i in range(2 * rx):  # the row's ends: their windows reflect
                c = i if i < rx else width - 2 * rx + i
                for dx in range(kx.size):
                    cols[dx] = reflect_101(c + dx - rx, width)
                count[c], total[c] = _censored_pixel(w, x, rows, cols, ky, kx, bound[c])
            _censored_fill(censored[r], x[r], count, total, image[r], bound_only[r])
            continue
        for c in range(width):
            if not censored[r, c]:
                continue
            for dx in range(kx.size):
                cols[dx] = reflect_101(c + dx - rx, width)
            count_c, total_c = _censored_pixel(w, x, rows, cols, ky, kx, censor / exposure[r, c])
            image[r, c] = max(total_c / max(count_c, np.float32(TINY)), x[r, c])
            if count_c <= np.float32(0.0):
                bound_only[r, c] = True


@kernel
def _censored_fill(censored, x, count, total, image, bound_only):
    """One row of :func:`_censored_each`'s result at its censored pixels from the window sums (vectorised)."""
    zero, tiny = np.float32(0.0), np.float32(TINY)
    for c in range(x.size):
        estimate = max(total[c] / max(count[c], tiny), x[c])
        image[c] = estimate if censored[c] else image[c]
        bound_only[c] |= censored[c] & (count[c] <= zero)


@kernel
def _censored_pixel(w, x, rows, cols, ky, kx, bound):
    """(weight, weighted sum) of the readings consistent with ``bound`` in the window of ``rows`` x ``cols``."""
    zero = np.float32(0.0)
    reach2 = np.float32(CONSISTENT_SIGMA * CONSISTENT_SIGMA)
    count, total = zero, zero
    for dy in range(ky.size):
        wr, xr, gy = w[rows[dy]], x[rows[dy]], ky[dy]
        for dx in range(kx.size):
            wq, xq = wr[cols[dx]], xr[cols[dx]]
            gap = bound - xq
            if wq > zero and (gap <= zero or wq * gap * gap <= reach2):
                g = gy * kx[dx]
                count += g
                total += g * xq
    return count, total


@kernel
def _censored_row(exposure, w, x, rows, ky, kx, censor, count, total, bound):
    """:func:`_censored_pixel` of every pixel of a row (``exposure`` its exposures) away from its ends, censored
    or not, into ``count`` and ``total``; the window's rows are ``rows``; ``bound`` gets censor / exposure."""
    zero = np.float32(0.0)
    width, rx = exposure.size, kx.size // 2
    for c in range(width):
        bound[c] = censor / exposure[c]
        count[c] = zero
        total[c] = zero
    n = width - 2 * rx
    inner_bound, inner_count, inner_total = bound[rx:rx + n], count[rx:rx + n], total[rx:rx + n]
    for dy in range(ky.size):
        gy, wr, xr = ky[dy], w[rows[dy]], x[rows[dy]]
        if kx.size == 3:
            _censored_taps3(wr, xr, inner_bound, gy * kx[0], gy * kx[1], gy * kx[2], inner_count, inner_total)
            continue
        for dx in range(kx.size):
            _censored_tap(wr[dx:dx + n], xr[dx:dx + n], inner_bound, gy * kx[dx], inner_count, inner_total)


@kernel
def _censored_taps3(w, x, bound, g0, g1, g2, count, total):
    """Three taps of :func:`_censored_row` in a row, w and x one row of the window (2 longer than ``bound``): one
    loop, which LLVM vectorises, adding them in :func:`_censored_tap`'s order."""
    zero = np.float32(0.0)
    reach2 = np.float32(CONSISTENT_SIGMA * CONSISTENT_SIGMA)
    for c in range(bound.size):
        b, n, t = bound[c], count[c], total[c]
        w0, x0, w1, x1, w2, x2 = w[c], x[c], w[c + 1], x[c + 1], w[c + 2], x[c + 2]
        gap = b - x0
        keep = (w0 > zero) & ((gap <= zero) | (w0 * gap * gap <= reach2))
        n += g0 if keep else zero
        t += g0 * x0 if keep else zero
        gap = b - x1
        keep = (w1 > zero) & ((gap <= zero) | (w1 * gap * gap <= reach2))
        n += g1 if keep else zero
        t += g1 * x1 if keep else zero
        gap = b - x2
        keep = (w2 > zero) & ((gap <= zero) | (w2 * gap * gap <= reach2))
        count[c] = n + (g2 if keep else zero)
        total[c] = t + (g2 * x2 if keep else zero)


@kernel
def _censored_tap(w, x, bound, g, count, total):
    """One tap of :func:`_censored_row`, over aligned 1-D arrays (a loop of its own, which LLVM vectorises)."""
    zero = np.float32(0.0)
    reach2 = np.float32(CONSISTENT_SIGMA * CONSISTENT_SIGMA)
    for c in range(bound.size):
        gap = bound[c] - x[c]
        keep = (w[c] > zero) & ((gap <= zero) | (w[c] * gap * gap <= reach2))
        count[c] += g if keep else zero
        total[c] += g * x[c] if keep else zero


@kernel
def _censored_separable(censored, exposure, w, x, image, bound_only, ky, kx, values, bounds):
    """The per-level window sums of :func:`_censored_pixels` (consistent readings, :func:`_consistent_row`, and
    their sum) at each censored pixel of (H, W) arrays, with OpenCV's arithmetic: a 3-tap row filter (centre tap
    + the pair around it), then a 3- or 5-tap column filter (centre, then the pairs outwards), borders
    reflect-101, each censored pixel's neighbours tested against its own level's bound (``bounds``, of the
    levels ``values``). Bit for bit the sums ``smooth`` gives there, at a cost that follows the censored pixels,
    not the number of levels: a row with few of them visits each one's window, a row with many (more than one in
    DENSE_ROW) sums every pixel's window at once, a loop over the row per window row (vectorised)."""
    h, width = censored.shape
    ry = ky.size // 2
    zero, tiny = np.float32(0.0), np.float32(TINY)
    reach = np.empty((h, width), np.float32)
    reached = np.zeros(h, np.bool_)
    rows = np.empty(ky.size, np.int64)
    bound = np.empty(width, np.float32)
    level_count, level_sum = np.empty((ky.size, width), np.float32), np.empty((ky.size, width), np.float32)
    count, total = np.empty(width, np.float32), np.empty(width, np.float32)
    leveled = np.empty(width, np.bool_)
    window_rows = np.arange(ky.size)
    for r in range(h):
        n = 0
        for c in range(width):
            n += censored[r, c]
        if n == 0:
            continue
        for dy in range(ky.size):
            rows[dy] = reflect_101(r + dy - ry, h)
        dense = n * DENSE_ROW > width
        _level_bounds(exposure[r], values, bounds, bound)
        for dy in range(ky.size):
            rr = rows[dy]
            if not reached[rr]:
                _reach_row(w[rr], x[rr], reach[rr])
                reached[rr] = True
        if dense:
            for dy in range(ky.size):
                _consistent_row_sums(reach[rows[dy]], x[rows[dy]], bound, kx[0], kx[1], level_count[dy],
                                     level_sum[dy])
            _column_sums(level_count, window_rows, ky, count)
            _column_sums(level_sum, window_rows, ky, total)
            for c in range(width):
                leveled[c] = censored[r, c] & (bound[c] < np.inf)
            _censored_fill(leveled, x[r], count, total, image[r], bound_only[r])
            continue
        for c in range(width):
            if not censored[r, c] or bound[c] == np.inf:
                continue
            for dy in range(ky.size):
                level_count[dy, 0], level_sum[dy, 0] = _consistent_pixel_sums(reach[rows[dy]], x[rows[dy]], c,
                                                                              bound[c], kx[0], kx[1])
            count_c, total_c = _column_sum_pixel(level_count[:, 0], ky), _column_sum_pixel(level_sum[:, 0], ky)
            image[r, c] = max(total_c / max(count_c, tiny), x[r, c])
            if count_c <= zero:
                bound_only[r, c] = True


@kernel
def _level_bounds(exposure, values, bounds, bound):
    """bound = bounds[j] where exposure == values[j], inf (no level: left alone) elsewhere; one row, vectorised."""
    for c in range(exposure.size):
        bound[c] = np.inf
    for j in range(values.size):
        value, level_bound = values[j], bounds[j]
        for c in range(exposure.size):
            bound[c] = level_bound if exposure[c] == value else bound[c]


@kernel
def _consistent_pixel_sums(reach, x, c, bound, k0, k1):
    """:func:`_consistent_row_sums` at pixel ``c`` of one row alone."""
    n = reach.size
    zero, one = np.float32(0.0), np.float32(1.0)
    left, right = reflect_101(c - 1, n), reflect_101(c + 1, n)
    a = zero if reach[left] < bound else one
    m = zero if reach[c] < bound else one
    d = zero if reach[right] < bound else one
    return k1 * m + k0 * (a + d), k1 * (m * x[c]) + k0 * (a * x[left] + d * x[right])


@kernel
def _column_sum_pixel(values, ky):
    """:func:`_column_sums` of one column (``values``: ky.size)."""
    if ky.size == 3:
        return ky[1] * values[1] + ky[0] * (values[0] + values[2])
    return ky[2] * values[2] + ky[1] * (values[1] + values[3]) + ky[0] * (values[0] + values[4])


@kernel
def _reach_row(w, x, reach):
    """x + CONSISTENT_SIGMA sqrt(1 / w) of uncensored readings (w > 0), -inf elsewhere, as :func:`_consistent_row`."""
    one, tiny, sigma = np.float32(1.0), np.float32(TINY), np.float32(CONSISTENT_SIGMA)
    none = np.float32(-np.inf)
    for k in range(w.size):
        reach[k] = np.sqrt(one / max(w[k], tiny)) * sigma + x[k] if w[k] > 0 else none


@kernel
def _consistent_row_sums(reach, x, bound, k0, k1, count, total):
    """The row filter (k0, k1, k0) of the consistent indicator (reach >= bound[c]) and of it times x, each pixel c
    of the row tested against ``bound[c]``; OpenCV's arithmetic, borders reflect-101."""
    n = reach.size
    zero, one = np.float32(0.0), np.float32(1.0)
    if n < 3:
        for c in range(n):
            left, right = reflect_101(c - 1, n), reflect_101(c + 1, n)
            a = zero if reach[left] < bound[c] else one
            b = zero if reach[c] < bound[c] else one
            d = zero if reach[right] < bound[c] else one
            count[c] = k1 * b + k0 * (a + d)
            total[c] = k1 * (b * x[c]) + k0 * (a * x[left] + d * x[right])
        return
    for c in (0, n - 1):
        left, right = reflect_101(c - 1, n), reflect_101(c + 1, n)
        a = zero if reach[left] < bound[c] else one
        b = zero if reach[c] < bound[c] else one
        d = zero if reach[right] < bound[c] else one
        count[c] = k1 * b + k0 * (a + d)
        total[c] = k1 * (b * x[c]) + k0 * (a * x[left] + d * x[right])
    r0, r1, r2, x0, x1, x2 = reach[:n - 2], reach[1:n - 1], reach[2:], x[:n - 2], x[1:n - 1], x[2:]
    b1, c1, t1 = bound[1:n - 1], count[1:n - 1], total[1:n - 1]
    for i in range(n - 2):
        b = b1[i]
        a = zero if r0[i] < b else one
        m = zero if r1[i] < b else one
        d = zero if r2[i] < b else one
        c1[i] = k1 * m + k0 * (a + d)
        t1[i] = k1 * (m * x1[i]) + k0 * (a * x0[i] + d * x2[i])


@kernel
def _column_sums(values, rows, ky, out):
    """The column filter ``ky`` (3 or 5 taps) over ``values``' rows ``rows`` (the window's, top to bottom):
    OpenCV's arithmetic, centre tap first, then the pairs outwards."""
    if ky.size == 3:
        a, b, c = values[rows[0]], values[rows[1]], values[rows[2]]
        k0, k1 = ky[0], ky[1]
        for i in range(out.size):
            out[i] = k1 * b[i] + k0 * (a[i] + c[i])
    else:
        a, b, c, d, e = values[rows[0]], values[rows[1]], values[rows[2]], values[rows[3]], values[rows[4]]
        k0, k1, k2 = ky[0], ky[1], ky[2]
        for i in range(out.size):
            out[i] = k2 * c[i] + k1 * (b[i] + d[i]) + k0 * (a[i] + e[i])


@kernel
def _level_boxes(censored, key, values, width, boxes):
    """Per level j, a box (first row, last row, first column, last column) holding its censored pixels.

    ``values``: the levels' keys, ascending (at most 63); a pixel's level is
    the number of keys below its own. The box of a level without censored
    pixels has last row -1.
    """
    rows = censored.size // width
    row_bits, col_bits = np.zeros(rows, np.int64), np.zeros(width, np.int64)
    slot = np.empty(width, np.int64)
    for r in range(rows):
        row = slice(r * width, (r + 1) * width)
        if censored[row].any():
            row_bits[r] = _row_level_bits(censored[row], key[row], values, slot, col_bits)
    for j in range(values.size):
        bit = np.int64(1) << j
        boxes[j, 0], boxes[j, 1] = _first_last(row_bits, bit)
        boxes[j, 2], boxes[j, 3] = _first_last(col_bits, bit)


@kernel
def _row_level_bits(censored, key, values, slot, col_bits):
    """Bit j set where a censored pixel of level j lies: in the row (returned), per column (OR-ed into col_bits)."""
    slot[:] = 0
    for j in range(values.size):
        for k in range(key.size):
            slot[k] += key[k] > values[j]
    bits = np.int64(0)
    for k in range(key.size):
        b = np.int64(censored[k]) << slot[k]
        bits |= b
        col_bits[k] |= b
    return bits


@kernel
def _first_last(bits, bit):
    """First and last index of ``bits`` with ``bit`` set; (size, -1) when none."""
    first, last = bits.size, -1
    for i in range(bits.size):
        if bits[i] & bit:
            first = min(first, i)
            last = i
    return first, last


@kernel
def _consistent(w, x, consistent, consistent_x, width, r0, c0, cols, bound):
    """Over a box of ``cols`` columns at (r0, c0): 1 for readings consistent with ``bound``, else 0; and that times x.

    Consistent: an uncensored reading (w > 0) whose reach x + 2 sqrt(v_p) is at least the bound.
    """
    for i in range(consistent.size // cols):
        start, out = (r0 + i) * width + c0, i * cols
        _consistent_row(w[start:start + cols], x[start:start + cols], consistent[out:out + cols],
                        consistent_x[out:out + cols], bound)


@kernel
def _consistent_row(w, x, consistent, consistent_x, bound):
    """One row of :func:`_consistent` (a loop of its own, which LLVM vectorises)."""
    zero, one, tiny, sigma = np.float32(0.0), np.float32(1.0), np.float32(TINY), np.float32(CONSISTENT_SIGMA)
    none = np.float32(-np.inf)  # no reading: consistent with no bound
    for k in range(w.size):
        reach = np.sqrt(one / max(w[k], tiny)) * sigma + x[k] if w[k] > 0 else none
        c = zero if reach < bound else one
        consistent[k] = c
        consistent_x[k] = c * x[k]


@kernel
def _fill_censored(censored, key, x, image, bound_only, count, sum_x, width, value, r0, c0, cols,
                   top, bottom, left, right):
    """At this level's censored pixels (key == value) in rows [top, bottom) and cols [left, right):
    image = max(mean of consistent x, x), from the window sums ``count`` and ``sum_x`` of a box of ``cols``
    columns at (r0, c0); flag empty windows.
    """
    n = right - left
    for r in range(top, bottom):
        at, box = r * width + left, (r - r0) * cols + left - c0
        _fill_row(censored[at:at + n], key[at:at + n], x[at:at + n], image[at:at + n], bound_only[at:at + n],
                  count[box:box + n], sum_x[box:box + n], value)


@kernel
def _fill_row(censored, key, x, image, bound_only, count, sum_x, value):
    """One row of :func:`_fill_censored` (a loop of its own, which LLVM vectorises)."""
    tiny = np.float32(TINY)
    for k in range(x.size):
        if censored[k] and key[k] == value:
            image[k] = max(sum_x[k] / max(count[k], tiny), x[k])
            if count[k] <= 0:
                bound_only[k] = True
