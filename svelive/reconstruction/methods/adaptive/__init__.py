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
   and the result is the window's noise-optimal mean. The weights favour precise
   readings, so beside a small bright feature the dark side outvotes it; p's own
   residual is evidence too: b^2 is at least (x_p - m)^2 - 25 (v_p + v_m), which
   noise alone passes at about one pixel in 1.7 million (strip_pass.OWN_SIGMA).
3. The minimum-mean-square combination of p's own reading and m:
   L^ = (x_p / v_p + m / (v_m + b^2)) / (1 / v_p + 1 / (v_m + b^2)), variance
   1 / (1 / v_p + 1 / (v_m + b^2)). In flat regions the window is averaged with
   noise-optimal weights; where the neighbours disagree with the pixel beyond
   their noise (edges, texture) b^2 grows and a well-exposed pixel keeps its own
   reading at full resolution; a noisy reading (short exposure, low light)
   counts for little either way. Where p's own residual passes OWN_SIGMA (it
   is not at its neighbours' level), the variance the result reports (steps 4
   and 5 read it) takes p's reading's model variance at the lower of the
   pilot's level and L^, not at the pilot's alone: beside light the pilot is
   the light's level, and a dark pixel's noise taken at it was lifted by
   step 4 to about three of its deviations above 0 (5 stops dim, dark rings
   2 px wide on a saturated disc; docs/peers.md).
4. Radiance is not negative: within 25 deviations of 0 the result is
   exp(E[log L]) of N(L^, variance) restricted to L >= 0 (:func:`nonnegative`),
   the estimate that minimises the expected squared error in log radiance
   (stops, as the project's metrics judge), never an exact 0; beyond, L^
   itself. A window whose readings all sit at raw 0 (clipped below) gives 0.
5. Where the result still cannot tell the level from 0 (L^ within
   CONTRAST_SIGMA deviations of it, an uncensored pixel), wider windows that
   are flat within their noise (:func:`wide_fallback`): the eight blocks of the
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
strip's rows (:func:`fused_pass`, svelive.jit): each window sum a row filter into a
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

from concurrent.futures import Executor
from functools import lru_cache
from typing import NamedTuple

import numpy as np

from svelive.reconstruction.methods.adaptive.censoring import censored_pixels, censored_way
from svelive.reconstruction.methods.adaptive.evidence import noise_model
from svelive.reconstruction.methods.adaptive.fallback import Dark, WIDE_SCALES, WeightRows, joined, wide_fallback
from svelive.reconstruction.methods.adaptive.parameters import CONTRAST_SIGMA, kernels
from svelive.reconstruction.methods.adaptive.posterior import POSTERIOR_HIGH, posterior_polynomial
from svelive.reconstruction.methods.adaptive.strip_pass import (
    SHARED_SUMS, PassNoise, PassOutputs, PassReadings, PassSettings, PassWindow, fused_pass, pattern_exposure_sum)
from svelive.reconstruction.methods.base import Estimate, SveInput, fill_lower_bounds, map_on, window_kernels


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
    return _same_window(inp.pattern.shape, inp.period)


@lru_cache(maxsize=16)
def _same_window(pattern_shape: tuple[int, int], period: tuple[int, int]) -> bool:
    """:func:`_shares_window` of an input of this exposure tile and tile ``period`` (asked a few times a live frame)."""
    ky, kx = kernels(pattern_shape)
    wy, wx = window_kernels(period)[:2]
    return (ky.size <= INLINE_WINDOW[0] and kx.size <= INLINE_WINDOW[1] and np.array_equal(ky, wy)
            and np.array_equal(kx, wx))


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
    _, lower, _, _, darks, _ = _estimate(inp, noise_model(inp), 1, want_darks=True)
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


def _estimate(inp: SveInput, noise: tuple[float, float], workers: int | Executor, want_variance: bool = False,
              want_share: bool = False, want_window: bool = False, want_darks: bool = False, out=None):
    """The method on a frame: (image, lower_bound, variance or None, share or None, the strips' Dark, the window
    mean and its variance as a (2, H, W) array, or of no rows without ``want_window``). A strip's Dark holds
    its estimate, information and candidates only where the wide fallback reads them (the strip has candidates),
    or with ``want_darks`` or ``want_share``; else they are freed with the strip (arrays of no rows).

    Steps 1-4 run in strips of about 64 rows (a window three deep above and
    below each, as base.in_strips does; the result does not depend on them),
    then the wide fallback over the strips holding pixels that cannot tell
    their level from 0, reading their neighbours' rows as far as its widest
    window reaches.

    ``out``: (image, lower, variance, window) arrays of the input's shape ((2, H, W) for the window) to write
    into instead of new ones (svelive.reconstruction.settle: views of a frame's rows), or None."""
    ky, kx = kernels(inp.pattern.shape)
    halo = 3 * (max(len(ky), len(kx)) // 2)  # pilot, neighbour estimate, bias: three windows deep
    spans = _spans(inp, halo, 64)
    h, w = inp.shape
    if out is not None:
        image, lower, variance, window = out
        if not want_window:
            window = np.empty((2, 0, 0), np.float32)
    else:
        image, lower = np.empty((h, w), np.float32), np.empty((h, w), bool)
        variance = np.empty((h, w), np.float32) if want_variance else None
        window = np.empty((2, h, w) if want_window else (2, 0, 0), np.float32)
    own = np.empty((h, w), np.float32) if want_share else None
    frame = _frame_settings(inp, noise, ky, kx)
    # the strips' weights (the fallback's) as rows of one array, each strip's computed rows after the last one's
    starts = np.cumsum([0] + [stop - start for start, _, _, stop in spans]).tolist()
    pool = WeightRows(np.empty((starts[-1], w), np.float32),
                      [first + top - start for first, (start, top, _, _) in zip(starts, spans)])

    def strip(i: int) -> Dark:
        # each strip's kept rows copied into the frame's arrays by its own thread (no serial join)
        start, top, bottom, stop = spans[i]
        crop = inp if (start, stop) == (0, inp.shape[0]) else inp.crop(slice(start, stop))
        keep = slice(top - start, bottom - start)
        # the image's, the variance's and the window's rows are written only in the kept rows: views of the frame's
        pieces = _solve(crop, frame, want_variance, want_share, keep, window[:, start:stop] if want_window else window,
                        image[start:stop], None if variance is None else variance[start:stop],
                        pool.rows[starts[i]:starts[i + 1]])
        for whole, piece in zip((lower, own), (pieces[1], pieces[3])):
            if whole is not None:
                whole[top:bottom] = piece[keep]
        dark = pieces[4].rows(keep)
        if dark.count or want_darks or want_share:
            return dark
        # the fallback reads only the weights of a strip without candidates (its neighbours' blocks reach it)
        return Dark(dark.weights, _NO_ROWS, _NO_ROWS, _NO_ROWS.astype(bool), 0)

    darks = map_on(workers, strip, range(len(spans)))
    if WIDE_SCALES > 0 and any(d.count for d in darks):
        wide_fallback(inp, spans, darks, image, variance, ky, kx, workers, pool)
    share = None
    if want_share:
        share = np.divide(own, joined([d.information for d in darks]))
    return image, lower, variance, share, darks, window


_NO_ROWS = np.empty((0, 0), np.float32)


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


class _Frame(NamedTuple):
    """What every strip's :func:`_solve` of one frame shares (made once a frame by :func:`_frame_settings`).

    Attributes:
        settings, noise: the fused pass's (strip_pass.PassSettings, PassNoise).
        window_noise: float32 (2,), (1 / g, sigma^2) of the sensor (strip_pass.PassWindow's ``noise``).
        way: censoring.censored_way of the frame.
        exposure_sums: the pattern's exposure window sums by strip shape (strip_pass.pattern_exposure_sum), filled
            as strips ask for them (a frame's strips have two or three shapes).
    """

    settings: PassSettings
    noise: PassNoise
    window_noise: np.ndarray
    way: str
    exposure_sums: dict


def _frame_settings(inp: SveInput, noise: tuple[float, float], ky: np.ndarray, kx: np.ndarray) -> _Frame:
    """The :class:`_Frame` of ``inp`` with noise model ``noise`` ((1 / gain, floor variance)) and kernels ky, kx."""
    f32 = np.float32
    kernel_square = f32((ky * ky).sum() * (kx * kx).sum())
    settings = PassSettings(ky, kx, f32(ky[len(ky) // 2] * kx[len(kx) // 2]), kernel_square,
                            f32(CONTRAST_SIGMA**2 * 2.0) * kernel_square, posterior_polynomial(),
                            -f32(inp.sensor.black_level), f32(CONTRAST_SIGMA**2))
    return _Frame(settings, PassNoise(f32(noise[0]), f32(noise[1])),
                  np.array([1.0 / inp.sensor.effective_gain, inp.sensor.floor_variance], f32),
                  censored_way(inp, ky, kx), {})


def _solve(inp: SveInput, frame: _Frame, want_variance: bool = False, want_share: bool = False,
           keep: slice | None = None, window: np.ndarray | None = None, image: np.ndarray | None = None,
           variance: np.ndarray | None = None, weights: np.ndarray | None = None):
    """Steps 1-4 on a whole frame or strip: (image, lower_bound, variance or None, w or None, Dark), (H, W)
    arrays whose rows ``keep`` (default all) hold the results; other rows are not set (the Dark's count is that of
    the rows ``keep``). ``window``: (2, H, W)
    float32 into whose rows ``keep`` the motion tests' window mean and variance go (:func:`fused_pass`), or None.
    ``image`` and ``variance`` (with ``want_variance``): float32 (H, W) to write the results into (only their rows
    ``keep``: views of a frame's rows, which other strips write around them), or None: new arrays. ``weights``:
    float32 (H, W) for the neighbours' weights wn (the Dark's; w itself where no reading is censored), or None: new.

    ``frame``: the frame's settings and noise model (:func:`_frame_settings`). The window sums and the
    per-pixel arithmetic between them run as one compiled pass (:func:`fused_pass`), then the censored pixels."""
    ky, kx = frame.settings.ky, frame.settings.kx
    f32 = np.float32
    shape = inp.shape
    first, last = (0, shape[0]) if keep is None else (keep.start, keep.stop)
    e, censored = inp.exposure, inp.censored
    flagged = bool(censored.any())
    exposure_sum = np.empty((0, 0), f32)  # computed in the pass
    # the pattern's, the same for every strip (a folded input's vary); with censored readings, where they are the
    # pass's own sums (it reads them only in windows without one)
    if not inp.folded and (not flagged or (len(ky), len(kx)) in SHARED_SUMS):
        if shape not in frame.exposure_sums:
            frame.exposure_sums[shape] = pattern_exposure_sum(inp.pattern, shape)
        cached, first_tile = frame.exposure_sums[shape]
        if np.array_equal(e[:first_tile.shape[0], :first_tile.shape[1]], first_tile):  # the pattern's phase
            exposure_sum = cached
    wn = np.empty(shape, f32) if weights is None else weights
    estimate, total = np.empty(shape, f32), np.empty(shape, f32)
    image = np.empty(shape, f32) if image is None else image
    # with censored pixels, the own weights w differ from wn, and the censored step reads x
    w, x = (np.empty(shape, f32), np.empty(shape, f32)) if flagged else (wn, np.empty((2 * (len(ky) // 2) + 1,
                                                                                        shape[1]), f32))
    lower, candidates = np.empty(shape, bool), np.empty(shape, bool)
    if variance is None or not want_variance:
        variance = np.empty(shape if want_variance else (0, 0), f32)
    every_row = flagged and frame.way == "levels"  # its sums read w and x on every row
    count, lowered = fused_pass(
        PassReadings(inp.signal, e, censored, flagged, every_row, exposure_sum), first, last, frame.noise,
        frame.settings, PassOutputs(w, wn, x, image, estimate, total, lower, candidates, variance),
        PassWindow(np.empty((2, 0, 0), f32) if window is None else window, frame.window_noise))
    if flagged:  # the pixels of the rows kept alone (OR-ed into lower): the strip's others are its neighbours'
        censored_pixels(inp, image, w, x, ky, kx, keep, out=lower)
        lowered = True  # whether any is: fill_lower_bounds looks
    if lowered:
        fill_lower_bounds(inp, lower, (len(ky), len(kx)), image, variance if want_variance else None, keep)
    return (image, lower, variance if want_variance else None, w if want_share else None,
            Dark(wn, estimate, total, candidates, count))
