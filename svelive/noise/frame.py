"""The noise model from the data: gain (electrons per DN) and read noise (DN) of a sensor, from its frames.

The model is the sensor's (svelive/core/sensor.py): a reading with expected signal
``s`` DN above black has variance ``s / gain + read_noise^2 + 1/12`` DN^2 (the
1/12 is uniform quantisation).

One frame (:func:`estimate_noise`). In an SVE frame the same radiance is seen
at several exposures a pixel apart. For a pixel ``p`` of exposure ``e_p`` and
its nearest same-colour neighbour ``q`` of a higher exposure ``e_q``, the
residual ``r = x_p - rho x_q`` (``rho = e_p / e_q``) is pure noise wherever the
scene is flat between them, with variance ``s_p (1 + rho) / g + (1 + rho^2) R``
(``R = read^2 + 1/12``). Because ``q`` is the longer exposure it predicts ``p``
far more precisely than ``p`` measures itself (``rho^2`` of the noise), and its
value ``rho x_q`` tells the signal of ``p`` without using ``p``'s own noise.

Texture is the enemy: it inflates every residual statistic (the older
single-frame estimate in svelive.calibrate.noise read 10-40x too high on real
scenes). Three things keep it out:

- A flatness test on *other* pixels: the four readings of ``q``'s exposure and
  colour one tile around ``q`` must vary (sample variance, in ``p``'s units) by
  no more than their own noise plus a small fraction of ``p``'s noise. Since the
  test sees neither ``x_p`` nor ``x_q``, it selects places without biasing the
  noise measured there.
- Per signal bin, a 3-sigma clipped mean of squared residuals (corrected for the
  clip), which drops edges and outliers; moments, not quantiles, because
  integer readings make quantiles of small residuals meaningless.
- A weighted line fit over the bins that drops bins lying well above the line
  (texture only ever inflates a bin), iterated.

Readings that may have clipped (near white, or within four noise standard
deviations of raw 0 when the black level is small) are left out on the strength
of the partner's value, again not their own. The flatness test uses the current
model, so the estimate is iterated from a deliberately strict start (small noise).

Texture that passes those tests still grows with the signal like shot noise, so a textured frame
reads the gain low. :func:`cancellation_fit` removes it: residuals of one geometry (colour, offset,
exposure ratio) at two or more base exposures ``e`` see the same texture scaled by ``e^2`` and
shot noise by ``e``. Taken in the same cells (all of a cell's residuals kept or dropped together,
binned and tested by the other cells of its block, never by their own readings), their bin means
are ``t / gain + R + c D`` with one unknown texture ``D`` per geometry and bin, fitted jointly
(:func:`joint_texture_fit`). :func:`estimate_noise` takes that fit where it tells the gain to
within 50 % and disagrees with the residual fit beyond its noise.

Over a stream (:class:`NoiseTracker`): the difference of two consecutive frames
at static pixels removes the scene altogether (variance ``2 (s / g + R)``); those
samples are pooled with every frame's single-frame samples, over a bounded
history, and the line is refitted.

The uncertainty is the weighted fit's covariance (bins weighted by the variance
of a variance estimate, ``2 v^2 / n``), scaled up by the reduced chi-square when
the bins scatter more than that. Texture that passes the flatness tests is a
fraction of the noise they test against, so it grows with the signal like shot
noise and the bins' scatter cannot show it: the slope's shift under a stricter
selection and under a texture term ``k t^2`` is added to its variance when
significant. The texture-cancelled fit's bins are correlated (shared readings, shared texture,
texture that differs between exposures over the frame): its variance is at least that of a
delete-one-band jackknife (:func:`_with_jackknife`). A value the frame does not tell carries the
prior's uncertainty.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, replace
from functools import lru_cache
from typing import TYPE_CHECKING

import numpy as np

from svelive.core.errors import SveliveError
from svelive.core.sensor import DEFAULT_FULL_WELL_E, DEFAULT_READ_NOISE_E, Sensor

if TYPE_CHECKING:  # the Camera is only read here (its pattern, colour filter and sensor)
    from svelive.core.camera import Camera

#: Variance of uniform quantisation to integers, DN^2.
QUANTISATION_VARIANCE = 1.0 / 12.0


@dataclass(frozen=True)
class EstimatorConfig:
    """Knobs of the single-frame estimator (the defaults are the documented method).

    Attributes:
        max_samples: pixel pairs used at most (a strided subset of the frame beyond that).
        flat_quantile: a place is flat when its neighbour groups' spread is below this quantile
            of the spread pure noise gives,
        region_quantile: and the residuals of its 3x3-tile block below this quantile of theirs.
        bins: signal bins at most.
        min_bin: samples per bin at least.
        outlier_tolerance: a bin more than this fraction (plus 3 standard errors) above the line is dropped.
        iterations: passes of select-fit after the first, model-free one.
        reach: farthest neighbour, pixels (Chebyshev distance).
        max_ratio: a neighbour's exposure is at least 1 / max_ratio times the pixel's.
        clip_sigma: per-bin clipping of squared residuals, in standard deviations.
        temporal_clip_sigma: the same for temporal samples alone (static pixels' frame differences):
            they hold no texture, only the odd missed motion, and a 3-sigma clip with the Gaussian
            correction reads the variance up to 17 % low where shot noise of a few electrons has
            heavier tails than a Gaussian (a low read noise beside a small full well).
        start_fraction: the first pass keeps this flattest fraction of every signal bin.
        max_shot_ratio: if > 0, the model passes leave out samples whose shot variance exceeds this
            many times the read noise's (off: it costs the read noise of bright frames their leverage).
        block: side of the sample blocks in tiles (odd); the region test uses the other samples of a block.
        texture_uncertainty: add to the fit's covariance the shift a texture term would make
            (:func:`_with_texture_uncertainty`),
        strict_fraction: and the shift a stricter selection makes (flat quantile times this, region
            median; 0: off; :func:`_with_selection_uncertainty`).
        cancellation: estimate the gain with texture cancelled across exposures (:func:`cancellation_fit`)
            where the pattern allows it, and keep it where it is known to within ``cancel_max_sigma``
            (relative); else the residuals above.
        cancel_bins: signal bins per geometry there;
        cancel_fraction: the flattest fraction of every bin kept (by the other cells of the block),
        cancel_flat: and every cell whose block's other cells are as flat as noise (their standardised
            residuals below the ``region_quantile`` of the chi-square noise alone gives; False: the
            fraction alone, as before issue 12.1's fifth pass);
        cancel_level: a cell's level may differ from its block's by this many times the lowest
            exposure's noise variance;
        cancel_mismatch: the relative difference allowed between the texture two exposures see;
        cancel_max_samples: residuals read at most (a strided subset of the frame beyond that);
        cancel_iterations: passes of select-fit there after the first (under the sensor defaults);
        cancel_jackknife: horizontal bands of the frame left out one at a time to measure the joint
            fit's spread (:func:`_with_jackknife`; 0: its own covariance alone).
        cancel_symmetric: where the nearest ring has symmetric and one-sided geometries, the joint fit
            of the symmetric ones alone is taken where the one-sided ones bias it
            (:func:`_without_gradient_bias`; issue 12.1, sixth pass; False: all of them, as before);
        cancel_when_biased: take a joint fit less precise than ``cancel_max_sigma`` where the residual
            fit's slope lies beyond two of the joint fit's standard deviations above it, or where there
            is no residual fit (:func:`_preferred`).
    """

    max_samples: int = 40_000
    flat_quantile: float = 0.5
    region_quantile: float = 0.75
    bins: int = 24
    min_bin: int = 100
    outlier_tolerance: float = 0.1
    iterations: int = 2
    reach: int = 2
    max_ratio: float = 0.13
    clip_sigma: float = 3.0
    temporal_clip_sigma: float = 8.0
    start_fraction: float = 0.25
    max_shot_ratio: float = 0.0
    block: int = 3
    texture_uncertainty: bool = True
    strict_fraction: float = 0.5
    cancellation: bool = True
    cancel_bins: int = 16
    cancel_fraction: float = 0.25
    cancel_flat: bool = True
    cancel_level: float = 1.0
    cancel_mismatch: float = 0.1
    cancel_max_sigma: float = 0.5
    cancel_max_samples: int = 400_000
    cancel_iterations: int = 1
    cancel_jackknife: int = 16
    cancel_symmetric: bool = True
    cancel_when_biased: bool = True


@dataclass(frozen=True)
class NoiseEstimate:
    """A sensor noise model and how well it is known.

    Attributes:
        gain: electrons per DN.
        read_noise: read noise, DN (standard deviation, quantisation excluded).
        gain_sigma: standard uncertainty of ``gain`` (e-/DN); 0 when given; the prior's (``ln 4`` times the
            value) when the data did not tell it; None when unknown.
        read_noise_sigma: standard uncertainty of ``read_noise`` (DN), likewise.
        samples: noise samples (pixel pairs; residuals when the texture-cancelled fit was taken) the
            estimate rests on.
        source: "given" (both from the user or datasheet), "estimated" (from the data,
            a given value kept), "default" (the data could not tell; the sensor defaults).
    """

    gain: float
    read_noise: float
    gain_sigma: float | None
    read_noise_sigma: float | None
    samples: int
    source: str

    @staticmethod
    def given(sensor: Sensor) -> NoiseEstimate:
        """The model of a sensor that gives both its gain and its read noise (source "given", no uncertainty)."""
        return NoiseEstimate(sensor.gain, sensor.read_noise, 0.0, 0.0, 0, "given")

    def to_dict(self) -> dict:
        """JSON-safe description (for /api/state): floats or None."""
        def num(v: float | None) -> float | None:
            return None if v is None or not math.isfinite(v) else float(v)
        return {"gain": num(self.gain), "read_noise": num(self.read_noise), "gain_sigma": num(self.gain_sigma),
                "read_noise_sigma": num(self.read_noise_sigma), "samples": int(self.samples),
                "source": self.source}

    def attributes(self) -> dict[str, float | str]:
        """Flat EXR header attributes (floats and a string); unknown uncertainties are left out."""
        out: dict[str, float | str] = {"noiseGain": float(self.gain), "noiseReadNoise": float(self.read_noise),
                                       "noiseSource": self.source}
        if self.gain_sigma is not None and math.isfinite(self.gain_sigma):
            out["noiseGainSigma"] = float(self.gain_sigma)
        if self.read_noise_sigma is not None and math.isfinite(self.read_noise_sigma):
            out["noiseReadNoiseSigma"] = float(self.read_noise_sigma)
        return out

    def apply(self, sensor: Sensor) -> Sensor:
        """``sensor`` with this gain and read noise where it has none (given values are never overridden)."""
        from dataclasses import replace

        return replace(sensor, gain=self.gain if sensor.gain is None else sensor.gain,
                       read_noise=self.read_noise if sensor.read_noise is None else sensor.read_noise)

    def describe(self) -> str:
        """One line for ``svelive reconstruct -v``."""
        def pm(v: float | None) -> str:
            return "" if v is None or not math.isfinite(v) or v == 0 else f" +- {v:.3g}"
        return (f"noise ({self.source}): gain {self.gain:.4g}{pm(self.gain_sigma)} e-/DN, read noise "
                f"{self.read_noise:.3g}{pm(self.read_noise_sigma)} DN, {self.samples} samples")


@dataclass(frozen=True)
class NoiseSamples:
    """Noise samples of one or more frames, each with a known expected value ``t / gain + R``.

    Attributes:
        t: float64 (N,), the shot-noise coordinate, DN (the signal, scaled by the residual's form).
        u: float64 (N,), the squared residual normalised so that E[u] = t / gain + R, DN^2.
    """

    t: np.ndarray
    u: np.ndarray

    @property
    def size(self) -> int:
        return int(self.t.size)

    @staticmethod
    def join(parts: list[NoiseSamples]) -> NoiseSamples:
        if not parts:
            return NoiseSamples(np.zeros(0), np.zeros(0))
        return NoiseSamples(np.concatenate([p.t for p in parts]), np.concatenate([p.u for p in parts]))


@dataclass(frozen=True)
class LineFit:
    """variance = slope * t + intercept, fitted over signal bins.

    Attributes:
        slope: 1 / gain, DN^2 per DN; intercept: R = read^2 + 1/12, DN^2; cov: 2x2 covariance of (slope, intercept).
        bins_t, bins_v, bins_n, inlier: the bins (signal, robust variance, count, kept by the fit).
    """

    slope: float
    intercept: float
    cov: np.ndarray
    bins_t: np.ndarray
    bins_v: np.ndarray
    bins_n: np.ndarray
    inlier: np.ndarray
    fixed_slope: bool = False
    texture: float = 0.0
    texture_sigma: float = 0.0

    def variance(self, t: np.ndarray | float) -> np.ndarray | float:
        return np.maximum(self.slope * np.asarray(t) + self.intercept, QUANTISATION_VARIANCE)


# ----- samples from one frame ----------------------------------------------------------------------


def _groups(tile_e: np.ndarray, tile_c: np.ndarray | None, a: int, b: int,
            reach: int, max_ratio: float) -> list[list[tuple[int, int]]]:
    """The neighbour groups that predict phase (a, b) of the joint tile: lists of offsets (dy, dx).

    Candidates have the pixel's colour and an exposure at least ``1 / max_ratio`` times its own: their
    readings are so much more precise that the flatness test they make is sharp on the scale of the
    pixel's noise. Symmetric pairs (k, -k) cancel any linear gradient, so pairs are preferred:
    those within one pixel when there are two or more, else within ``reach``. Without two pairs,
    single neighbours of the nearest ring holding two or more, highest exposures first (at most four).
    Fewer than two groups: [] (the phase is not used).
    """
    ph, pw = tile_e.shape
    e0 = tile_e[a, b]

    def ok(dy: int, dx: int) -> bool:
        qa, qb = (a + dy) % ph, (b + dx) % pw
        return ((dy, dx) != (0, 0) and tile_e[qa, qb] * max_ratio >= e0 * 0.999
                and (tile_c is None or tile_c[qa, qb] == tile_c[a, b]))

    def exposure(dy: int, dx: int) -> float:
        return float(tile_e[(a + dy) % ph, (b + dx) % pw])

    for r in range(1, reach + 1):
        ring = [(dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1) if ok(dy, dx)]
        pairs = [[k, (-k[0], -k[1])] for k in ring if k > (-k[0], -k[1]) and (-k[0], -k[1]) in ring]
        if len(pairs) >= 2:
            return pairs
    for r in range(1, reach + 1):
        ring = [(dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1) if ok(dy, dx)]
        if len(ring) >= 2:
            ring.sort(key=lambda k: (-exposure(*k), k[0] * k[0] + k[1] * k[1], k))
            return [[k] for k in ring[:4]]
    return []


@dataclass(frozen=True)
class _PhaseData:
    """One tile phase's samples, gathered once and re-selected at every iteration.

    Samples come in blocks of 3x3 neighbouring tiles; ``block`` says which.

    Attributes:
        xp: float64 (N,), the pixel's signal, DN.
        m: float64 (G, N), each group's prediction of it (exposure-scaled mean of the group), DN.
        rho: float64 (G, N), the pixel's exposure over the group's.
        size: float64 (G, 1), readings per group.
        block: int64 (N,), the block of every sample.
        blocks: number of blocks.
        s_groups: float64 (G, N), each group's own signal, ``max(m / rho, 0)``, DN.
        scale: float64 (G, N), ``rho^2 / size``: a group prediction's variance over one reading's.
        others: float64 (N,), the other samples of the sample's block.
        region_limit: float64 (N,), the region test's limit on their summed standardised squares.
    """

    xp: np.ndarray
    m: np.ndarray
    rho: np.ndarray
    size: np.ndarray
    block: np.ndarray
    blocks: int
    s_groups: np.ndarray
    scale: np.ndarray
    others: np.ndarray
    region_limit: np.ndarray


def _block_lines(first: int, stop: int, period: int, stride: int, side: int) -> np.ndarray:
    """Rows (or columns) of blocks ``side`` tiles wide (odd): centres every ``stride`` tiles, each with the
    tile lines around it; int64 (side B,), grouped by block."""
    half = side // 2
    centres = np.arange(first + half * period, stop - half * period, period * stride)
    return (centres[:, None] + period * np.arange(-half, half + 1)[None, :]).ravel()


def _gather(source: np.ndarray, offset: float, pixel_map: np.ndarray | None, tile_e: np.ndarray,
            tile_c: np.ndarray | None, high: float, config: EstimatorConfig) -> list[_PhaseData]:
    """Every usable phase's pixels (in 3x3-tile blocks, a strided subset of the frame) with their groups'
    predictions.

    ``source - offset`` is the signal above black (raw (H, W) and the black level, or a linear
    signal and 0); exposures are the tile's, or ``pixel_map``'s (H, W) where calibrated.
    ``high``: signal (DN) at or above which a reading may be clipped; a sample touching one is dropped.
    """
    signal = source
    ph, pw = tile_e.shape
    h, w = signal.shape
    reach = config.reach
    phases = [(a, b, g) for a in range(ph) for b in range(pw)
              if (g := _groups(tile_e, tile_c, a, b, reach, config.max_ratio))]
    if not phases:
        return []
    tiles = (h // ph) * (w // pw)
    side = config.block
    # each block holds side^2 tiles; one block per stride x stride tiles
    stride = max(side, int(math.ceil(math.sqrt(side * side * tiles * len(phases) / config.max_samples))))
    out = []
    for a, b, groups in phases:
        first_y = a + ph * (-(-(reach - a) // ph)) if a < reach else a
        first_x = b + pw * (-(-(reach - b) // pw)) if b < reach else b
        rows = _block_lines(first_y, h - reach, ph, stride, side)
        cols = _block_lines(first_x, w - reach, pw, stride, side)
        if rows.size == 0 or cols.size == 0:
            continue
        by, bx = rows.size // side, cols.size // side
        block = (np.arange(by)[:, None, None, None] * bx + np.arange(bx)[None, None, :, None])
        block = np.broadcast_to(block, (by, side, bx, side)).ravel()

        def at(dy: int, dx: int) -> np.ndarray:
            values = signal[np.ix_(rows + dy, cols + dx)].astype(np.float64).ravel()
            values -= offset
            return values

        def exposure(dy: int, dx: int) -> np.ndarray | float:
            if pixel_map is None:
                return float(tile_e[(a + dy) % ph, (b + dx) % pw])
            return pixel_map[np.ix_(rows + dy, cols + dx)].astype(np.float64).ravel()

        xp, ep = at(0, 0), exposure(0, 0)
        ok = xp < high
        m, rho = [], []
        for group in groups:
            values = [at(dy, dx) for dy, dx in group]
            scales = [np.broadcast_to(ep / exposure(dy, dx), xp.shape) for dy, dx in group]
            for v in values:
                ok &= v < high
            m.append(sum(v * c for v, c in zip(values, scales)) / len(group))
            rho.append(sum(scales) / len(group))
        size = np.array([[len(g)] for g in groups], np.float64)
        m_ok, rho_ok = np.ascontiguousarray(np.stack(m)[:, ok]), np.ascontiguousarray(np.stack(rho)[:, ok])
        block_ok = block[ok]
        others = np.bincount(block_ok, None, by * bx)[block_ok] - 1.0
        out.append(_PhaseData(xp[ok], m_ok, rho_ok, size, block_ok, by * bx, np.maximum(m_ok / rho_ok, 0.0),
                              rho_ok * rho_ok / size, others,
                              _chi2_quantile_array(config.region_quantile, others)))
    return out


def _chi2_quantile(q: float, dof: int) -> float:
    """Quantile of chi-square with ``dof`` degrees of freedom (Wilson-Hilferty approximation)."""
    z = _normal_quantile(q)
    t = 2.0 / (9.0 * dof)
    return dof * max(1.0 - t + z * math.sqrt(t), 0.0) ** 3


def _normal_quantile(q: float) -> float:
    from statistics import NormalDist

    return NormalDist().inv_cdf(q)


def _select(data: _PhaseData, model: tuple[float, float], floor: float, high: float,
            config: EstimatorConfig, ranked: bool,
            strict: EstimatorConfig | None = None) -> tuple[NoiseSamples, np.ndarray, NoiseSamples | None]:
    """The phase's samples at flat, unclipped places under the model ``(slope, intercept)``.

    Two flatness tests, neither of which sees the pixel's own reading (so selecting on them does
    not bias its noise):

    - its neighbour groups: their predictions, combined with inverse-variance weights into ``m``,
      spread as ``T = sum w_k (m_k - m)^2``, chi-square with G - 1 degrees of freedom where the
      scene is linear, larger on texture;
    - its region: the other samples of its 3x3-tile block, whose standardised squared residuals
      average ``Z``, chi-square with (n - 1) degrees of freedom over n - 1 where the block is
      flat; texture comes in regions (foliage, fabric), so a pixel whose group test passed by
      chance in a textured region is caught.

    With ``ranked`` the caller keeps the flattest by ``T * Z`` (returned), else places below the
    ``flat_quantile`` of both chi-squares are kept here; with ``strict`` also the samples that pass
    that configuration's quantiles (third item, else None).
    """
    slope, intercept = model
    s_groups, others = data.s_groups, data.others
    weights = 1.0 / (data.scale * np.maximum(slope * s_groups + intercept, QUANTISATION_VARIANCE))
    total = weights.sum(axis=0)
    omega = weights / total
    m = (omega * data.m).sum(axis=0)
    spread = (weights * (data.m - m) ** 2).sum(axis=0)
    coef = omega * omega * data.scale  # var(m) = sum coef (slope s_k + R)
    big_b = 1.0 + coef.sum(axis=0)
    t = (m + (coef * s_groups).sum(axis=0)) / big_b
    r = data.xp - m
    u = r * r / big_b
    var_p = np.maximum(slope * np.maximum(m, 0.0) + intercept, QUANTISATION_VARIANCE)
    z = u / np.maximum(slope * t + intercept, QUANTISATION_VARIANCE)
    block_sum = np.bincount(data.block, z, data.blocks)
    region_sum = block_sum[data.block] - z
    sd_p = np.sqrt(var_p)
    keep = (m - floor >= 4.0 * sd_p) & (m + 4.0 * sd_p < high) & (others >= 4)
    # the neighbours too must be unlikely to clip (their readings near ``high`` were dropped, which
    # would truncate their noise and bias the prediction)
    top = s_groups.max(axis=0)
    keep &= top + 4.0 * np.sqrt(np.maximum(slope * top + intercept, QUANTISATION_VARIANCE)) < high
    dof = data.m.shape[0] - 1
    stricter = None
    if not ranked:
        if strict is not None:
            sel = (keep & (spread <= _chi2_quantile(strict.flat_quantile, dof))
                   & (region_sum <= _chi2_quantile_array(strict.region_quantile, others)))
            stricter = NoiseSamples(t=t[sel], u=u[sel])
        keep &= spread <= _chi2_quantile(config.flat_quantile, dof)
        keep &= region_sum <= data.region_limit
    return (NoiseSamples(t=t[keep], u=u[keep]), (spread / dof * region_sum / np.maximum(others, 1))[keep],
            stricter)


def _chi2_quantile_array(q: float, dof: np.ndarray) -> np.ndarray:
    """:func:`_chi2_quantile` for an array of degrees of freedom (>= 1), float64."""
    z = _normal_quantile(q)
    d = np.maximum(dof, 1).astype(np.float64)
    t = 2.0 / (9.0 * d)
    return d * np.maximum(1.0 - t + z * np.sqrt(t), 0.0) ** 3


def _select_all(data: list[_PhaseData], model: LineFit | tuple[float, float] | None, floor: float,
                high: float, sensor: Sensor, config: EstimatorConfig,
                strict: EstimatorConfig | None = None) -> tuple[NoiseSamples, NoiseSamples | None]:
    """Samples of every phase, and with ``strict`` (and a model) those that pass its quantiles too.
    Without a model (the first pass) the weights take the sensor defaults
    and the flattest ``start_fraction`` of every signal bin is kept, by T times Z: within a bin the
    samples have about the same noise, so the ranking does not depend on the noise scale."""
    ranked = model is None
    if model is None:
        model = (1.0 / sensor.effective_gain, sensor.floor_variance)
    elif isinstance(model, LineFit):
        model = (model.slope, model.intercept)
    parts, spreads, stricter = [], [], []
    for phase in data:
        samples, spread, strict_samples = _select(phase, model, floor, high, config, ranked, strict)
        parts.append(samples)
        spreads.append(spread)
        if strict_samples is not None:
            stricter.append(strict_samples)
    joined = NoiseSamples.join(parts)
    if not ranked or joined.size == 0:
        return joined, (NoiseSamples.join(stricter) if strict is not None and not ranked else None)
    spread = np.concatenate(spreads)
    which, _ = _bin_index(joined.t, config.bins)
    # within every bin, keep the spreads at or below its start_fraction quantile (linear interpolation):
    # exactly those at or below the value of sorted rank floor((n - 1) q)
    order = np.lexsort((spread, which))
    counts = np.bincount(which, minlength=config.bins)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    rank = starts + np.floor((np.maximum(counts, 1) - 1) * config.start_fraction).astype(np.int64)
    limit = spread[order[np.minimum(rank, joined.size - 1)]]
    keep = spread <= limit[which]
    return NoiseSamples(joined.t[keep], joined.u[keep]), None


# ----- robust statistics and the line fit -------------------------------------------------------------


def _normal_cdf(x: np.ndarray) -> np.ndarray:
    """Standard normal CDF, float64, |error| < 2e-7 (Abramowitz and Stegun 7.1.26 for erf)."""
    z = np.abs(x) / math.sqrt(2.0)
    k = 1.0 / (1.0 + 0.3275911 * z)
    poly = k * (0.254829592 + k * (-0.284496736 + k * (1.421413741 + k * (-1.453152027 + k * 1.061405429))))
    erf = 1.0 - poly * np.exp(-z * z)
    return 0.5 * (1.0 + np.sign(x) * erf)


@lru_cache(maxsize=1)
def _median_table() -> tuple[np.ndarray, np.ndarray]:
    """(sigma^2 + 1/12, median of (g + q)^2) for g ~ N(0, sigma^2) and q ~ U(-1/2, 1/2), over a sigma grid:
    the median of a rounded reading's squared residual, which for small sigma is not 0.455 of the variance.
    Read-only arrays, computed once."""
    sigmas = np.geomspace(0.05, 100.0, 100)[:, None]
    u = ((np.arange(32) + 0.5) / 32 - 0.5)[None, :]  # quadrature over the rounding error
    lo, hi = np.zeros_like(sigmas), 0.5 + 8 * sigmas
    for _ in range(36):  # bisection on P(|g + q| <= x) = 1/2
        x = 0.5 * (lo + hi)
        p = np.mean(_normal_cdf((x - u) / sigmas) - _normal_cdf((-x - u) / sigmas), axis=1, keepdims=True)
        lo, hi = np.where(p < 0.5, x, lo), np.where(p < 0.5, hi, x)
    variance, medians = sigmas[:, 0] ** 2 + QUANTISATION_VARIANCE, (0.5 * (lo + hi))[:, 0] ** 2
    variance.setflags(write=False)
    medians.setflags(write=False)
    return variance, medians


def _variance_from_median(median: float, table: tuple[np.ndarray, np.ndarray]) -> float:
    """The variance (DN^2, quantisation included) whose rounded-Gaussian residual has this median square."""
    variance, medians = table
    if median >= medians[-1]:
        return median / 0.45493642  # Gaussian: the median of chi-square with one degree of freedom
    return float(np.interp(median, medians, variance))


def _clip_correction(k: float) -> float:
    """E[z^2 | |z| < k] for a standard normal z: the factor a k-sigma clipped mean square falls short by."""
    phi = math.exp(-0.5 * k * k) / math.sqrt(2 * math.pi)
    return 1.0 - 2.0 * k * phi / math.erf(k / math.sqrt(2))


def _median_and_quantile(u: np.ndarray, q: float) -> tuple[float, float]:
    """``np.median(u)`` and ``np.quantile(u, q)`` (linear interpolation, numpy's formula) from one
    partial sort of ``u`` (float64 (N,), N >= 1)."""
    n = u.size
    pos = q * (n - 1)
    lo = int(math.floor(pos))
    kth = sorted({(n - 1) // 2, n // 2, lo, min(lo + 1, n - 1)})
    part = np.partition(u, kth)
    median = float(part[n // 2]) if n % 2 else 0.5 * (float(part[n // 2 - 1]) + float(part[n // 2]))
    a, b, frac = float(part[lo]), float(part[min(lo + 1, n - 1)]), pos - lo
    top = b - (b - a) * (1.0 - frac) if frac >= 0.5 else a + (b - a) * frac
    return median, top


def _robust_variance(u: np.ndarray, clip_sigma: float, table: tuple[np.ndarray, np.ndarray]) -> float:
    """Variance (DN^2) from squared residuals ``u`` (noise, plus texture and edges in a minority).

    The mean of ``u`` below ``clip_sigma^2`` times the variance, corrected for the clip and
    iterated. A mean, not a quantile: residuals of integer readings
    take discrete values where the signal barely varies, and a quantile of those jumps.
    """
    # start from above (the mean of all but the top percent) and clip down to the fixed point: from
    # below, integer residuals of small noise (mostly 0 and +-1) would stop the clip short
    median, top = _median_and_quantile(u, 0.99)
    v = max(_variance_from_median(median, table), float(np.mean(u[u <= top])))
    corr = _clip_correction(clip_sigma)
    count = -1
    for _ in range(6):
        inside = u <= clip_sigma * clip_sigma * v
        kept = int(np.count_nonzero(inside))
        if kept == 0 or kept == count:  # the same samples as the last pass: converged
            break
        count = kept
        v = float(np.dot(u, inside)) / kept / corr
    return v


def _bin_index(t: np.ndarray, bins: int) -> tuple[np.ndarray, np.ndarray]:
    """The bin of every sample, int64 (N,), bins equally spaced in log(t + 2 DN) over the samples' range,
    and the bin edges in t, float64 (bins + 1,)."""
    coord = np.log(np.maximum(t, 0.0) + 2.0)
    lo, hi = float(coord.min()), float(coord.max())
    which = np.minimum(((coord - lo) / max(hi - lo, 1e-9) * bins).astype(np.int64), bins - 1)
    return which, np.exp(np.linspace(lo, hi, bins + 1)) - 2.0


def bin_samples(samples: NoiseSamples, config: EstimatorConfig, *,
                temporal: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Signal bins, equally spaced in log(t + 2 DN): (mean t, robust variance, count), float64/float64/int64 (B,).

    The variance of a bin is read from the median of its squared residuals (half the samples may
    be texture or edges without moving it), through the rounded-Gaussian table; bins with fewer
    than ``config.min_bin`` samples are left out. ``temporal`` (samples that hold no texture): clipped
    at ``config.temporal_clip_sigma``, and the count is the effective one, ``2 v^2 / var(u)`` times the
    count, so that the fit's Gaussian weights give the bin's measured standard error (shot noise of a
    few electrons is heavier-tailed than a Gaussian, and its variance estimates scatter more).
    """
    if temporal:
        config = replace(config, clip_sigma=config.temporal_clip_sigma)
    if samples.size < config.min_bin:
        return np.zeros(0), np.zeros(0), np.zeros(0, np.int64)
    table = _median_table()
    which, _ = _bin_index(samples.t, config.bins)
    order = np.argsort(which, kind="stable")
    counts = np.bincount(which, minlength=config.bins)
    starts = np.concatenate([[0], np.cumsum(counts)])
    t, v, c = [], [], []
    for k in range(config.bins):
        if counts[k] < config.min_bin:
            continue
        idx = order[starts[k]:starts[k + 1]]
        t.append(float(np.mean(samples.t[idx])))
        v.append(_robust_variance(samples.u[idx], config.clip_sigma, table))
        count = int(counts[k])
        if temporal:
            u = samples.u[idx]
            u = u[u <= config.clip_sigma**2 * v[-1]]
            spread = float(np.var(u)) if u.size > 1 else 0.0
            count = int(min(count, max(2.0 * v[-1] ** 2 * u.size / spread, 1.0))) if spread > 0 else count
        c.append(count)
    return np.array(t), np.array(v), np.array(c, np.int64)


def fit_line(t: np.ndarray, v: np.ndarray, n: np.ndarray, *, slope: float | None = None,
             intercept: float | None = None, outlier_tolerance: float = 0.1,
             texture: bool = False) -> LineFit | None:
    """Weighted least squares of ``v = slope * t + intercept`` over bins, dropping bins well above the line.

    Each bin weighs ``n / (2 model^2)`` (a variance estimate's variance is ``2 v^2 / n``). A bin
    more than ``outlier_tolerance`` plus three standard errors above the line is dropped (texture only
    inflates); one far below (four standard errors and the tolerance) too. A given ``slope`` or
    ``intercept`` is held fixed. With ``texture`` a term ``k t^2`` (``k >= 0``) is fitted too and
    left out of the noise: texture that survives the flatness tests is a contrast, its variance
    grows as the signal squared where shot noise grows as the signal (``LineFit.texture`` is ``k``;
    the covariance of slope and intercept then includes what not knowing ``k`` costs).
    None when fewer than 2 bins (3 for both free) remain or the slope is not positive.
    """
    t, v, n = (np.asarray(a, np.float64) for a in (t, v, n))
    free = [slope is None, intercept is None]
    need = 1 + sum(free)
    if t.size < need:
        return None
    quad = texture and free[0] and t.size >= need + 2
    inlier = np.ones(t.size, bool)
    model = np.maximum(v, QUANTISATION_VARIANCE)
    coef = np.array([slope or 0.0, intercept or 0.0, 0.0])
    cov = np.zeros((2, 2))

    def design(with_quad: bool) -> np.ndarray:
        cols = [c for c, f in zip((t, np.ones_like(t)), free) if f] + ([t * t] if with_quad else [])
        return np.stack(cols, axis=1)

    def solve(w: np.ndarray) -> tuple[np.ndarray, bool]:
        target = v - (0.0 if slope is None else slope * t) - (0.0 if intercept is None else intercept)
        for with_quad in ((True, False) if quad else (False,)):
            sol, *_ = np.linalg.lstsq(design(with_quad) * w[:, None], target * w, rcond=None)
            if not with_quad or sol[-1] >= 0:
                break
        k = 0
        out = np.array([slope or 0.0, intercept or 0.0, 0.0])
        for j, f in enumerate(free):
            if f:
                out[j] = sol[k]
                k += 1
        if with_quad:
            out[2] = sol[-1]
        return out, with_quad

    used_quad = False
    for _ in range(8):
        w = np.sqrt(n / 2.0) / model * inlier
        if int(inlier.sum()) < need + used_quad:
            return None
        coef, used_quad = solve(w)
        model_new = np.maximum(coef[0] * t + coef[1] + coef[2] * t * t, QUANTISATION_VARIANCE)
        se = model_new * np.sqrt(2.0 / n)
        new_inlier = ((v <= model_new * (1 + outlier_tolerance) + 3 * se)
                      & (v >= model_new * (1 - outlier_tolerance) - 4 * se))
        converged = np.array_equal(new_inlier, inlier) and np.allclose(model_new, model, rtol=1e-4)
        model, inlier = model_new, new_inlier
        if converged:
            break
        if int(inlier.sum()) < need + used_quad:
            return None
    w = np.sqrt(n / 2.0) / model * inlier
    a = design(used_quad) * w[:, None]
    dof = max(int(inlier.sum()) - need - used_quad, 1)
    resid = (v - model) * w
    chi2 = float(np.sum(resid * resid)) / dof
    try:
        sub = np.linalg.inv(a.T @ a) * max(chi2, 1.0)
    except np.linalg.LinAlgError:
        return None
    idx = [k for k, f in enumerate(free) if f]
    for i, ki in enumerate(idx):
        for j, kj in enumerate(idx):
            cov[ki, kj] = sub[i, j]
    if not coef[0] > 0:
        return None
    texture_sigma = math.sqrt(max(float(sub[-1, -1]), 0.0)) if used_quad else 0.0
    return LineFit(float(coef[0]), float(coef[1]), cov, t, v, n.astype(np.int64), inlier, not free[0],
                   float(coef[2]), texture_sigma)


#: The prior every estimate is combined with: log-normal around the sensor defaults (sensor.py), one
#: standard deviation a factor of 4 (full wells of 2 500-40 000 e- for 12 bits are within one sigma).
PRIOR_LOG_SIGMA = math.log(4.0)


def _prior_sigma(default: float) -> float:
    """The standard uncertainty of a value the data did not tell (the prior's alone): its log-sigma times
    the value, so that ``2 sigma`` spans the factor the prior allows (about 16 either way)."""
    return PRIOR_LOG_SIGMA * default


def _with_prior(value: float, sigma: float, default: float) -> tuple[float, float]:
    """Combine an estimate and its standard uncertainty with the log-normal prior around ``default``.

    A well-measured value barely moves (at 15 % uncertainty the prior weighs about 1 %); a value the
    data hardly constrains falls back towards the default instead of swinging wide.
    """
    s_est = sigma / max(value, 1e-12)
    if not math.isfinite(s_est) or s_est <= 0:
        return value, sigma
    w_est, w_prior = 1.0 / s_est**2, 1.0 / PRIOR_LOG_SIGMA**2
    log_v = (w_est * math.log(max(value, 1e-12)) + w_prior * math.log(default)) / (w_est + w_prior)
    post = math.exp(log_v)
    return post, post / math.sqrt(w_est + w_prior)


def _gain_log_sigma(fit: LineFit) -> float:
    """The gain's uncertainty as a log-sigma: ``-ln(1 - sigma / slope)``, the gain's rise where the slope
    is one standard deviation lower (the side on which ``1 / slope`` grows without bound). For a
    well-measured slope this is ``sigma / slope``; for a slope hardly above its noise it is large,
    where ``sigma / slope`` would state an overestimated slope's gain to within a factor of 2."""
    rel = math.sqrt(max(fit.cov[0, 0], 0.0)) / fit.slope
    return -math.log(max(1.0 - rel, 1e-6))


def estimate_from_fit(fit: LineFit | None, sensor: Sensor, samples: int) -> NoiseEstimate:
    """The NoiseEstimate of a fitted line: the sensor's given values kept, each estimated value combined
    with the prior (:func:`_with_prior`), the defaults where the fit failed (source "default")."""
    given_gain, given_read = sensor.gain, sensor.read_noise
    if given_gain is not None and given_read is not None:
        return NoiseEstimate(given_gain, given_read, 0.0, 0.0, samples, "given")
    default_gain = given_gain if given_gain is not None else DEFAULT_FULL_WELL_E / sensor.range_dn
    default_read = DEFAULT_READ_NOISE_E / default_gain
    if fit is None:
        read = given_read if given_read is not None else default_read
        return NoiseEstimate(default_gain, read, 0.0 if given_gain is not None else _prior_sigma(default_gain),
                             0.0 if given_read is not None else _prior_sigma(read), samples, "default")
    if given_gain is not None:
        gain, gain_sigma = given_gain, 0.0
    elif fit.fixed_slope:  # the data told only the read noise; the gain stays the default, as uncertain as the prior
        gain, gain_sigma = default_gain, _prior_sigma(default_gain)
    else:
        gain = 1.0 / fit.slope
        gain, gain_sigma = _with_prior(gain, gain * _gain_log_sigma(fit), default_gain)
    if given_read is not None:
        read, read_sigma = given_read, 0.0
    else:
        read = math.sqrt(max(fit.intercept - QUANTISATION_VARIANCE, 0.0))
        sd_r = math.sqrt(max(fit.cov[1, 1], 0.0))
        # below about one standard error of the variance the read noise is known only to be small
        read_sigma = sd_r / (2 * read) if read > math.sqrt(sd_r) else math.sqrt(sd_r)
        read, read_sigma = _with_prior(max(read, 0.05), read_sigma, DEFAULT_READ_NOISE_E / default_gain)
    return NoiseEstimate(gain, read, gain_sigma, read_sigma, samples, "estimated")


# ----- texture cancellation across exposures ---------------------------------------------------------


@dataclass(frozen=True)
class _Residual:
    """A residual ``x_p - mean_k(e_p / e_q x_q)`` of the pixel at tile phase (a, b) and its neighbours at
    ``offsets`` (dy, dx) from it, all of one exposure ``e_q >= e_p`` and of the pixel's colour."""

    a: int
    b: int
    offsets: tuple[tuple[int, int], ...]


def _cancellation_geometries(tile_e: np.ndarray, tile_c: np.ndarray | None,
                             reach: int) -> list[list[_Residual]]:
    """Residuals of the same geometry at two or more base exposures, grouped by geometry.

    A geometry is a colour, an offset ``k`` (symmetric ``(k, -k)`` where both sides have the same
    exposure, which cancels a linear gradient; else one side) and an exposure ratio ``e_q / e_p >= 1``.
    Its residuals see the scene's texture at that offset scaled by ``e_p``, so with two base exposures
    texture (``e_p^2``) and shot noise (``e_p``) can be told apart. Only the nearest ring that gives
    any geometry is used (nearer neighbours, less texture). [] when the pattern has none (one exposure
    per colour, or no two base exposures sharing a geometry).
    """
    ph, pw = tile_e.shape

    def exposure(y: int, x: int) -> float:
        return float(tile_e[y % ph, x % pw])

    def colour(y: int, x: int) -> int | None:
        return None if tile_c is None else int(tile_c[y % ph, x % pw])

    for r in range(1, reach + 1):
        ring = [(dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1)
                if max(abs(dy), abs(dx)) == r and (dy, dx) > (-dy, -dx)]
        found: dict[tuple, list[tuple[_Residual, float]]] = {}
        for a in range(ph):
            for b in range(pw):
                e_p, c_p = exposure(a, b), colour(a, b)
                for k in ring:
                    plus, minus = (a + k[0], b + k[1]), (a - k[0], b - k[1])
                    ok_plus = colour(*plus) == c_p and exposure(*plus) >= e_p
                    ok_minus = colour(*minus) == c_p and exposure(*minus) >= e_p
                    if ok_plus and ok_minus and exposure(*plus) == exposure(*minus):
                        key = (c_p, k, 2, exposure(*plus) / e_p)
                        found.setdefault(key, []).append((_Residual(a, b, (k, (-k[0], -k[1]))), e_p))
                        continue
                    for sign, ok, q in ((1, ok_plus, plus), (-1, ok_minus, minus)):
                        # a pair of equal exposures is the same pair seen from either end: once
                        if ok and not (sign < 0 and exposure(*q) == e_p):
                            key = (c_p, k, 1, exposure(*q) / e_p)
                            found.setdefault(key, []).append((_Residual(a, b, ((sign * k[0], sign * k[1]),)), e_p))
        groups = [[res for res, _ in items] for items in found.values() if len({e for _, e in items}) >= 2]
        if groups:
            return groups
    return []


def _disjoint_cells(reads: set[tuple[int, int]], ph: int, pw: int) -> tuple[int, int]:
    """The smallest cell (rows, columns; multiples of the tile) such that the readings of a cell and of
    any cell up to two cells away are disjoint: a cell's binning and flatness statistics come from the
    other cells of its block, and must not see its own readings."""
    best = (8 * ph, 8 * pw)
    for my in range(1, 8):
        for mx in range(1, 8):
            cy, cx = my * ph, mx * pw
            if cy * cx >= best[0] * best[1]:
                continue
            shifts = [(i * cy, j * cx) for i in range(-2, 3) for j in range(-2, 3) if (i, j) != (0, 0)]
            if all((d[0] + sy, d[1] + sx) not in reads for d in reads for sy, sx in shifts):
                best = (cy, cx)
    return best


@dataclass(frozen=True)
class _CellData:
    """One geometry's readings in blocks of 3x3 cells, gathered once and re-selected at every iteration.

    Attributes:
        x: float64 (K, N), the K readings of every cell (signal above black, DN).
        e: float64 (K, 1), their exposures.
        u: float64 (J, N), each residual's square, normalised so that ``E[u] = t / gain + R + c D``
            (``D`` the texture of the geometry at that level), DN^2.
        t: float64 (J, N), the shot coordinate from the cell's own readings (unbiased), DN.
        c: float64 (J,), the texture coefficient ``e_p^2 / sum coef^2``.
        block: int64 (N,), the block of every cell; blocks: number of blocks; others: float64 (N,),
            the other cells of the block.
        symmetric: every residual of the geometry has neighbours on both sides (cancels a gradient).
    """

    x: np.ndarray
    e: np.ndarray
    u: np.ndarray
    t: np.ndarray
    c: np.ndarray
    block: np.ndarray
    blocks: int
    others: np.ndarray
    symmetric: bool


def _cancellation_gather(source: np.ndarray, offset: float, tile_e: np.ndarray, groups: list[list[_Residual]],
                         high: float, config: EstimatorConfig) -> list[_CellData]:
    """Every geometry's readings in blocks of 3x3 cells (a strided subset of the frame, about
    ``config.cancel_max_samples`` residuals in all). A cell with a reading at or above ``high`` is dropped."""
    ph, pw = tile_e.shape
    h, w = source.shape
    side = config.block
    total = sum(len(g) for g in groups)
    out = []
    for group in groups:
        reads = sorted({(r.a + d[0], r.b + d[1]) for r in group for d in ((0, 0), *r.offsets)})
        cy, cx = _disjoint_cells(set(reads), ph, pw)
        lo_y, hi_y = max(0, -min(d[0] for d in reads)), max(0, max(d[0] for d in reads))
        lo_x, hi_x = max(0, -min(d[1] for d in reads)), max(0, max(d[1] for d in reads))
        first_y, first_x = lo_y + (-lo_y) % ph, lo_x + (-lo_x) % pw
        cells = max((h - first_y - hi_y) // cy, 0) * max((w - first_x - hi_x) // cx, 0)
        stride = max(side, int(math.ceil(side * math.sqrt(cells * total / config.cancel_max_samples))))
        rows = _block_lines(first_y, h - hi_y - cy + 1, cy, stride, side)
        cols = _block_lines(first_x, w - hi_x - cx + 1, cx, stride, side)
        if rows.size == 0 or cols.size == 0:
            continue
        by, bx = rows.size // side, cols.size // side
        block = np.broadcast_to(np.arange(by)[:, None, None, None] * bx + np.arange(bx)[None, None, :, None],
                                (by, side, bx, side)).ravel()
        x = np.stack([source[np.ix_(rows + dy, cols + dx)].astype(np.float64).ravel() for dy, dx in reads])
        x -= offset
        ok = np.all(x < high, axis=0)
        index = {d: k for k, d in enumerate(reads)}
        e = np.array([[float(tile_e[dy % ph, dx % pw])] for dy, dx in reads])
        coef = np.zeros((len(group), len(reads)))
        for j, res in enumerate(group):
            e_p = float(tile_e[res.a % ph, res.b % pw])
            coef[j, index[(res.a, res.b)]] = 1.0
            for dy, dx in res.offsets:
                q = index[(res.a + dy, res.b + dx)]
                coef[j, q] -= e_p / e[q, 0] / len(res.offsets)
        x, block = np.ascontiguousarray(x[:, ok]), block[ok]
        # a residual r = coef . x has variance sum coef^2 (e L / g + R) + texture; normalised by sum coef^2
        size = (coef * coef).sum(axis=1)
        r = coef @ x
        e_p = (coef > 0) @ e[:, 0]
        others = np.bincount(block, None, by * bx)[block] - 1.0
        out.append(_CellData(x, e, r * r / size[:, None], ((coef * coef) @ x) / size[:, None], e_p * e_p / size,
                             block, by * bx, others, all(len(r.offsets) == 2 for r in group)))
    return out


@dataclass(frozen=True)
class _CancellationSamples:
    """One geometry's selected cells.

    Attributes:
        coord: float64 (N,), the binning coordinate, ``log(L e_max + 2)`` of the level ``L`` of the
            other cells of the block (never of the cell's own readings).
        u: float64 (J, N), squared residuals normalised so that ``E[u] = t / gain + R + c D``, DN^2.
        t: float64 (J, N), the shot coordinate from the cell's own readings (unbiased), DN.
        c: float64 (J,), the texture coefficient ``e_p^2 / sum coef^2``.
        region: int64 (N,), the horizontal band of the frame the cell's block lies in, in
            ``[0, config.cancel_jackknife)`` (the units :func:`_with_jackknife` leaves out).
        symmetric: the geometry's residuals have neighbours on both sides (:func:`_without_gradient_bias`).
    """

    coord: np.ndarray
    u: np.ndarray
    t: np.ndarray
    c: np.ndarray
    region: np.ndarray
    symmetric: bool


def _cancellation_select(data: _CellData, model: tuple[float, float], floor: float, high: float,
                         config: EstimatorConfig) -> _CancellationSamples | None:
    """The cells of one geometry at flat, unclipped places under the model ``(slope, intercept)``; all of a
    cell's residuals are kept or dropped together, so every exposure sees the same texture.

    - The level ``L`` of a cell is its readings' generalised-least-squares mean (weights
      ``e / var``): for Gaussian noise it is independent of every residual, whose mean is 0 on a flat
      scene. The level of the other cells of its block bins it and tests its clipping.
    - Flat at the cell scale: the lowest exposure sees the cell's level and its block's differ by
      at most its noise (``config.cancel_level`` times its variance).
    - Flat around it: within every bin the ``config.cancel_fraction`` of cells whose block's other
      cells have the smallest standardised residuals are kept, and (``config.cancel_flat``) every cell
      whose block's other cells are as flat as noise: their standardised residuals, chi-square with
      (residuals x cells) degrees of freedom where the block is flat, below its ``config.region_quantile``.
      Where texture is small against the noise (dark or flat places) a fixed fraction would throw
      usable cells away; where it dominates, the fraction still applies.
    None when fewer than ``config.min_bin`` cells remain.
    """
    slope, intercept = model
    x, e = data.x, data.e
    if x.shape[1] < config.min_bin:
        return None
    level = x.sum(axis=0) / e.sum()
    weights = e / np.maximum(slope * e * np.maximum(level, 0.0) + intercept, QUANTISATION_VARIANCE)
    level = (weights * x).sum(axis=0) / (weights * e).sum(axis=0)
    count = data.others
    around = (np.bincount(data.block, level, data.blocks)[data.block] - level) / np.maximum(count, 1.0)
    keep = count >= 4
    # clipping, tested at every distinct exposure from the block's level and from the cell's own
    for e_k in np.unique(e[:, 0]):
        for lv in (around, level):
            sd = np.sqrt(np.maximum(slope * e_k * np.maximum(lv, 0.0) + intercept, QUANTISATION_VARIANCE))
            keep &= (e_k * lv - 4.0 * sd >= floor) & (e_k * lv + 4.0 * sd < high)
    e_low = float(e.min())
    var_low = np.maximum(slope * e_low * np.maximum(around, 0.0) + intercept, QUANTISATION_VARIANCE)
    keep &= (e_low * (level - around)) ** 2 <= config.cancel_level * var_low
    if np.count_nonzero(keep) < config.min_bin:
        return None
    u, t = data.u, data.t
    z = (u / np.maximum(slope * np.maximum(t, 0.0) + intercept, QUANTISATION_VARIANCE)).sum(axis=0)
    region = (np.bincount(data.block, z, data.blocks)[data.block] - z) / np.maximum(count, 1.0)
    coord = np.log(np.maximum(around, 0.0) * float(e.max()) + 2.0)
    which = _bins_of(coord, keep, config.cancel_bins)
    # within every bin, the cells at or below its cancel_fraction quantile of the region statistic
    limit = np.full(config.cancel_bins, -np.inf)
    for k in range(config.cancel_bins):
        inside = region[keep & (which == k)]
        if inside.size:
            limit[k] = np.quantile(inside, config.cancel_fraction)
    flattest = region <= limit[which]
    if config.cancel_flat:
        # and wherever the block is as flat as noise: the others' summed z is chi-square with J per cell
        cells = np.maximum(count, 1.0)
        flattest |= region <= _chi2_quantile_array(config.region_quantile, u.shape[0] * cells) / cells
    keep &= flattest
    if np.count_nonzero(keep) < config.min_bin:
        return None
    region = data.block[keep] * max(config.cancel_jackknife, 1) // data.blocks
    return _CancellationSamples(coord[keep], u[:, keep], t[:, keep], data.c, region, data.symmetric)


def _bins_of(coord: np.ndarray, where: np.ndarray, bins: int) -> np.ndarray:
    """Equal-width bins of ``coord`` over its range at ``where``: int64 (N,) in [0, bins)."""
    lo, hi = float(coord[where].min()), float(coord[where].max())
    return np.clip(((coord - lo) / max(hi - lo, 1e-9) * bins).astype(np.int64), 0, bins - 1)


def _cancellation_table(parts: list[_CancellationSamples], config: EstimatorConfig) -> tuple[np.ndarray, ...]:
    """Per geometry, bin and residual: (group id, mean t, c, mean u, count), float64/.../int64 (M,) each;
    a group is one geometry's bin (its texture is one unknown). Bins with fewer than ``config.min_bin``
    cells are left out."""
    gid, t, c, u, n = [], [], [], [], []
    group = 0
    for part in parts:
        which = _bins_of(part.coord, np.ones(part.coord.shape, bool), config.cancel_bins)
        counts = np.bincount(which, minlength=config.cancel_bins)
        sum_t = np.stack([np.bincount(which, tj, config.cancel_bins) for tj in part.t])
        sum_u = np.stack([np.bincount(which, uj, config.cancel_bins) for uj in part.u])
        for k in np.flatnonzero(counts >= config.min_bin):
            for j in range(part.u.shape[0]):
                gid.append(group)
                t.append(sum_t[j, k] / counts[k])
                c.append(part.c[j])
                u.append(sum_u[j, k] / counts[k])
                n.append(counts[k])
            group += 1
    return (np.array(gid, np.int64), np.array(t), np.array(c), np.array(u), np.array(n, np.int64))


def joint_texture_fit(gid: np.ndarray, t: np.ndarray, c: np.ndarray, u: np.ndarray, n: np.ndarray, *,
                      slope: float | None = None, intercept: float | None = None,
                      mismatch: float = 0.1) -> LineFit | None:
    """Weighted least squares of ``u = slope t + intercept + c D_g`` with one texture ``D_g`` per group.

    A group holds the bins of one geometry and signal level at two or more base exposures: texture
    scales as ``c`` (the exposure squared), shot noise as ``t`` (the exposure), so the two are told
    apart and the texture ``D_g`` (of any sign: a bound would keep only the groups whose texture
    happened to fluctuate up, and bias the slope) is fitted away. A bin mean's variance is
    ``2 m^2 / n`` (``m`` the fitted value) plus ``(mismatch * c D_g)^2``: the texture two exposures
    see is equal only to within ``mismatch`` (they sample neighbouring rows or columns), so bins where
    texture dominates weigh little. The covariance is scaled up by the reduced chi-square. A given
    ``slope`` or ``intercept`` is held fixed. None when the system is underdetermined or the slope
    not positive. The texture unknowns are profiled out group by group (no matrix with a column per
    group), which gives the same line and covariance as the full least squares.
    """
    groups = int(gid.max()) + 1 if gid.size else 0
    free = [slope is None, intercept is None]
    cols = np.array([a for a, f in zip((t, np.ones_like(t)), free) if f])
    if u.size < groups + len(cols) + 2 or not len(cols):
        return None
    target = u - (slope or 0.0) * t - (intercept or 0.0)
    fitted = np.maximum(u, QUANTISATION_VARIANCE)
    tex = np.zeros_like(u)
    for _ in range(6):
        w2 = 1.0 / (2.0 * fitted * fitted / n + (mismatch * tex) ** 2)
        # the texture unknowns profiled out (Frisch-Waugh-Lovell): within each group the part of the
        # line's columns and of the target that c explains is removed, and the line's own weighted least
        # squares on what is left gives the joint solution's slope, intercept and covariance exactly
        # (a 2x2 system instead of one with a column per group)
        cc = np.bincount(gid, w2 * c * c, groups)[gid]
        x_res = cols - c * np.stack([np.bincount(gid, w2 * c * col, groups)[gid] for col in cols]) / cc
        y_res = target - c * np.bincount(gid, w2 * c * target, groups)[gid] / cc
        normal = (x_res * w2) @ x_res.T
        sol = np.linalg.pinv(normal) @ ((x_res * w2) @ y_res)
        resid = y_res - sol @ x_res
        tex = np.abs(target - sol @ cols - resid)  # |c D_g|
        fitted = np.maximum(u - resid, QUANTISATION_VARIANCE)
    dof = max(u.size - groups - len(cols), 1)
    chi2 = float((resid * resid * w2).sum()) / dof
    sub = np.linalg.pinv(normal) * max(chi2, 1.0)
    coef = [slope or 0.0, intercept or 0.0]
    cov = np.zeros((2, 2))
    idx = [k for k, f in enumerate(free) if f]
    for i, ki in enumerate(idx):
        coef[ki] = float(sol[i])
        for j, kj in enumerate(idx):
            cov[ki, kj] = sub[i, j]
    if not coef[0] > 0 or not np.all(np.isfinite(cov)):
        return None
    return LineFit(coef[0], coef[1], cov, t, u, n, np.ones(u.size, bool), not free[0])


def cancellation_fit(source: np.ndarray, offset: float, floor: float, camera: Camera,
                     config: EstimatorConfig = EstimatorConfig(), start: LineFit | None = None) -> LineFit | None:
    """The noise line of one frame with texture cancelled across exposures (see the module docstring and
    docs/noise.md), or None where the pattern, the frame or the fit cannot give it (no geometry at two
    base exposures, a calibrated per-pixel exposure map, too few flat cells, an ill-posed fit).

    ``source - offset`` is the signal above black; ``floor`` the lowest signal a reading can take (DN).
    ``start``: a line the selection's first pass may use (the residual fit of the same frame), which
    saves the pass under the sensor defaults.
    """
    tile_e, tile_c, pixel_map = _layout(camera)
    groups = _cancellation_geometries(tile_e, tile_c, config.reach)
    if not groups or pixel_map is not None:
        return None
    sensor = camera.sensor
    high = _high_level(sensor)
    data = _cancellation_gather(source, offset, tile_e, groups, high, config)
    fixed = _fixed(sensor)
    model = (fixed["slope"] or 1.0 / sensor.effective_gain,
             fixed["intercept"] if fixed["intercept"] is not None else sensor.floor_variance)
    passes = 1 + config.cancel_iterations
    if start is not None:
        model, passes = (start.slope, max(start.intercept, QUANTISATION_VARIANCE)), config.cancel_iterations
    fit = None
    for _ in range(max(passes, 1)):
        parts = [p for d in data if (p := _cancellation_select(d, model, floor, high, config)) is not None]
        if not parts:
            return None
        fit = joint_texture_fit(*_cancellation_table(parts, config), **fixed, mismatch=config.cancel_mismatch)
        if fit is None:
            return None
        model = (fit.slope, max(fit.intercept, QUANTISATION_VARIANCE))
    if fit is not None and config.cancel_jackknife > 1:
        fit = _with_jackknife(fit, parts, fixed, config)
    if fit is not None and config.cancel_symmetric:
        fit = _without_gradient_bias(fit, parts, fixed, config)
    return fit


def _without_gradient_bias(fit: LineFit, parts: list[_CancellationSamples], fixed: dict,
                           config: EstimatorConfig) -> LineFit:
    """``fit``, or the joint fit of its symmetric geometries alone where the one-sided ones bias it.

    A one-sided residual keeps the scene's gradient, which base exposures a row or more apart see
    differently (``1/1/8/8``: three one-sided geometries across rows beside the pairs along the row):
    a bias that more data does not shrink, while their residuals make the fit more precise (small
    frames need them). The same selected cells are fitted without them; where the two slopes agree
    within two of the symmetric fit's standard deviations and ``fit`` states the smaller uncertainty,
    ``fit`` is kept, else the symmetric fit (as :func:`_preferred` weighs the residual fit against the
    joint one)."""
    symmetric = [p for p in parts if p.symmetric]
    if not symmetric or len(symmetric) == len(parts):
        return fit
    sym = joint_texture_fit(*_cancellation_table(symmetric, config), **fixed, mismatch=config.cancel_mismatch)
    if sym is None:
        return fit
    if config.cancel_jackknife > 1:
        sym = _with_jackknife(sym, symmetric, fixed, config)
    return fit if _no_bias_shown(fit, sym) else sym


def _no_bias_shown(precise: LineFit, unbiased: LineFit) -> bool:
    """True where the slope of ``precise`` (a fit open to a bias) lies within two of the ``unbiased`` fit's
    standard deviations of its slope and ``precise`` states the smaller uncertainty: then the data show no
    bias and the more precise fit is the better one."""
    return (precise.slope - unbiased.slope) ** 2 <= 4.0 * unbiased.cov[0, 0] and precise.cov[0, 0] <= unbiased.cov[0, 0]


def _with_jackknife(fit: LineFit, parts: list[_CancellationSamples], fixed: dict,
                    config: EstimatorConfig) -> LineFit:
    """``fit`` with its covariance raised to the delete-one-band jackknife's where that is larger.

    The fit's own covariance treats every bin mean as independent with the variance of ``n``
    independent squared residuals. They are not: a cell's residuals share readings, neighbouring
    cells share texture, and what the two exposures of a geometry see differs by a texture that
    varies over the frame. Leaving out one horizontal band of blocks at a time
    (``config.cancel_jackknife`` bands, all geometries together, the bins kept) and refitting the
    same selected cells measures the spread all of these give, whatever their correlation, without
    a model of it. The line itself is left as fitted."""
    bands = config.cancel_jackknife
    sums = []  # per geometry: counts (bands, bins), sums of t and u (J, bands, bins), c (J,)
    for part in parts:
        which = _bins_of(part.coord, np.ones(part.coord.shape, bool), config.cancel_bins)
        index = part.region * config.cancel_bins + which
        size = bands * config.cancel_bins
        counts = np.bincount(index, minlength=size).reshape(bands, config.cancel_bins)
        sum_t = np.stack([np.bincount(index, tj, size) for tj in part.t]).reshape(-1, bands, config.cancel_bins)
        sum_u = np.stack([np.bincount(index, uj, size) for uj in part.u]).reshape(-1, bands, config.cancel_bins)
        sums.append((counts, sum_t, sum_u, part.c))
    estimates = []
    for g in range(bands):
        gid, t, c, u, n = [], [], [], [], []
        group = 0
        for counts, sum_t, sum_u, coef in sums:
            cnt = counts.sum(axis=0) - counts[g]
            st = sum_t.sum(axis=1) - sum_t[:, g]
            su = sum_u.sum(axis=1) - sum_u[:, g]
            for k in np.flatnonzero(cnt >= config.min_bin):
                gid += [group] * coef.size
                t += list(st[:, k] / cnt[k])
                c += list(coef)
                u += list(su[:, k] / cnt[k])
                n += [cnt[k]] * coef.size
                group += 1
        other = joint_texture_fit(np.array(gid, np.int64), np.array(t), np.array(c), np.array(u),
                                  np.array(n, np.int64), **fixed, mismatch=config.cancel_mismatch)
        if other is None:
            return fit  # a band the fit cannot do without: the jackknife is undefined
        estimates.append((other.slope, other.intercept))
    est = np.array(estimates)
    dev = est - est.mean(axis=0)
    jack = (bands - 1) / bands * (dev.T @ dev)
    extra = np.maximum(np.diag(jack) - np.diag(fit.cov), 0.0)
    return replace(fit, cov=fit.cov + np.diag(extra))


# ----- the public single-frame estimate ---------------------------------------------------------------


def _layout(camera: Camera) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """The joint tile's nominal exposures and channels (ph, pw), and the calibrated per-pixel map or None."""
    pattern = camera.require_pattern()
    period = camera.period
    reps = lambda tile: np.tile(tile, (period[0] // tile.shape[0], period[1] // tile.shape[1]))  # noqa: E731
    tile_e = reps(np.asarray(pattern.tile, np.float64))
    tile_c = None if camera.cfa is None else reps(np.asarray(camera.cfa.tile))
    return tile_e, tile_c, pattern.pixel_map


def _signal_of(raw: np.ndarray, camera: Camera, signal: np.ndarray | None) -> tuple[np.ndarray, float, float]:
    """(array, offset, floor): the linear signal above black is ``array - offset`` (no full-frame copy is
    made); ``floor`` is the lowest signal a reading can take (DN)."""
    sensor = camera.sensor
    raw = camera.check(raw)
    if signal is not None:
        signal = np.asarray(signal)
        if signal.shape != raw.shape:
            raise SveliveError(f"signal has shape {signal.shape} but the raw frame {raw.shape}")
        # a response's linearisation clips at black; raw frames clip at raw 0
        return signal, 0.0, 0.0 if camera.response is not None else -float(sensor.black_level)
    if camera.response is not None:
        raise SveliveError("this camera has a response curve: give the linearised signal "
                           "(signal=svelive.reconstruction.input.prepare(raw, camera).signal)")
    return raw, float(sensor.black_level), -float(sensor.black_level)


def _high_level(sensor: Sensor) -> float:
    """Signal (DN) from which a reading may be clipped at white: two percent below the range."""
    return 0.98 * sensor.range_dn


def frame_samples(raw: np.ndarray, camera: Camera, *, signal: np.ndarray | None = None,
                  config: EstimatorConfig = EstimatorConfig()) -> tuple[NoiseSamples, LineFit | None]:
    """The single-frame estimator's flat-place samples of one frame and the line fitted to them."""
    source, offset, floor = _signal_of(raw, camera, signal)
    tile_e, tile_c, pixel_map = _layout(camera)
    high = _high_level(camera.sensor)
    data = _gather(source, offset, pixel_map, tile_e, tile_c, high, config)
    if sum(d.xp.size for d in data) < 3 * config.min_bin:
        return NoiseSamples(np.zeros(0), np.zeros(0)), None
    fixed = _fixed(camera.sensor)
    model: LineFit | None = None
    fit, samples, stricter = None, NoiseSamples(np.zeros(0), np.zeros(0)), None
    strict = replace(config, flat_quantile=config.flat_quantile * config.strict_fraction, region_quantile=0.5)
    for step in range(1 + config.iterations):
        last = step == config.iterations and config.strict_fraction > 0
        samples, stricter = _select_all(data, model, floor, high, camera.sensor, config, strict if last else None)
        if model is not None and config.max_shot_ratio:
            # texture grows as the signal squared, shot noise as the signal: beyond a shot variance of
            # a few times the read noise's, bins add more bias than information about the gain
            keep = samples.t * model.slope <= config.max_shot_ratio * max(model.intercept, 1.0)
            samples = NoiseSamples(samples.t[keep], samples.u[keep])
        fit = fit_line(*bin_samples(samples, config), **fixed, outlier_tolerance=config.outlier_tolerance)
        if fit is None:
            break
        model = fit
    if fit is None and fixed["slope"] is None and fixed["intercept"] is None and samples.size:
        # too narrow a signal range for the slope: the read noise alone, the gain held at the default,
        # from the bins where even a gain at the prior's low end (a quarter of the default) leaves
        # shot noise under half the variance (elsewhere a wrong gain would pass its shot noise off
        # as read noise)
        slope = 1.0 / camera.sensor.effective_gain
        t, v, n = bin_samples(samples, config)
        dark = math.exp(PRIOR_LOG_SIGMA) * slope * t <= 0.5 * v
        fit = fit_line(t[dark], v[dark], n[dark], slope=slope, outlier_tolerance=config.outlier_tolerance)
    elif fit is not None and config.texture_uncertainty and not fit.fixed_slope:
        fit = _with_texture_uncertainty(fit, fixed, config)
        if stricter is not None:
            fit = _with_selection_uncertainty(fit, stricter, fixed, config)
    return samples, fit


def _with_selection_uncertainty(fit: LineFit, stricter: NoiseSamples, fixed: dict,
                                config: EstimatorConfig) -> LineFit:
    """``fit`` with the shift a stricter selection (``stricter``: the samples of the last pass that
    passed it) makes in its covariance.

    Neither flatness test sees the pixel's own reading, so a stricter selection changes only how much
    texture gets through, never the noise measured: the line moves only if texture is biasing it.
    Texture that passed the tests scales with the noise they test against (its contribution grows
    with the signal like shot noise, and the bins cannot tell them apart), so this shift, not the
    scatter of the bins, is what says that a textured frame cannot give the gain. The estimate
    itself stays the one of the usual selection (the strict one has fewer samples)."""
    other = fit_line(*bin_samples(stricter, config), **fixed, outlier_tolerance=config.outlier_tolerance)
    if other is None:
        return fit
    return _add_systematic(fit, other)


def _add_systematic(fit: LineFit, other: LineFit) -> LineFit:
    """``fit`` with the shift of the slope to ``other`` (a fit of the same bins with a texture term, or of
    a subset of its samples: noisier either way) added to the slope's variance as a systematic error
    when it is significant, beyond two standard deviations of the noise the two fits do not share
    (for nested estimates the difference has variance ``var_other - var_fit``). Texture vanishes at
    zero signal, so it biases the slope (the gain); the intercept is left as fitted."""
    delta = other.slope - fit.slope
    if delta * delta <= 4.0 * max(other.cov[0, 0] - fit.cov[0, 0], 0.0):
        return fit
    return replace(fit, cov=fit.cov + np.diag([delta * delta, 0.0]))


def _with_texture_uncertainty(fit: LineFit, fixed: dict, config: EstimatorConfig) -> LineFit:
    """``fit`` with what texture may have added to it in its covariance.

    Texture that passed the flatness tests is a contrast: its variance grows as the signal squared.
    The same bins fitted with a term ``k t^2`` (k >= 0) give another line; the shift from ``fit`` to
    it is what the frame cannot tell between shot noise and texture, and is added to the
    covariance (:func:`_add_systematic`)."""
    alt = fit_line(fit.bins_t, fit.bins_v, fit.bins_n, **fixed, outlier_tolerance=config.outlier_tolerance,
                   texture=True)
    if alt is None:
        return fit
    if alt.texture > 2.0 * alt.texture_sigma:
        cov = fit.cov.copy()
        cov[0, 0] = max(cov[0, 0], alt.cov[0, 0])
        fit = replace(fit, cov=cov)
    return _add_systematic(fit, alt)


def _fixed(sensor: Sensor) -> dict:
    """The given parts of the noise model, held fixed in the fit."""
    return {"slope": None if sensor.gain is None else 1.0 / sensor.gain,
            "intercept": None if sensor.read_noise is None else sensor.read_noise**2 + QUANTISATION_VARIANCE}


def estimate_noise(raw: np.ndarray, camera: Camera, *, signal: np.ndarray | None = None,
                   config: EstimatorConfig = EstimatorConfig()) -> NoiseEstimate:
    """Gain and read noise of the camera's sensor from one raw SVE frame.

    Args:
        raw: uint8/uint16 (H, W) raw DN as delivered, black level included.
        camera: exposure pattern, colour filter (pairs are same-colour), black and white level;
            a given gain or read noise is kept (and held fixed in the fit of the other).
        signal: float32 (H, W), the linear signal above black when the camera has a response
            curve (``prepare(raw, camera).signal``); by default ``raw - black``.
    Returns:
        the estimate; ``source`` "default" (with the sensor defaults) when the frame has too few
        flat unclipped places (a tiny, saturated or blank frame).
    """
    sensor = camera.sensor
    if sensor.gain is not None and sensor.read_noise is not None:
        return NoiseEstimate.given(sensor)
    fit, count = frame_fit(raw, camera, signal=signal, config=config)
    return estimate_from_fit(fit, sensor, count)


def frame_fit(raw: np.ndarray, camera: Camera, *, signal: np.ndarray | None = None,
              config: EstimatorConfig = EstimatorConfig()) -> tuple[LineFit | None, int]:
    """The noise line :func:`estimate_noise` takes from one frame and the samples behind it: the
    residual fit (:func:`frame_samples`), or the texture-cancelled one (:func:`cancellation_fit`)
    where :func:`_preferred` takes it; (None, n) when the frame gives no line."""
    samples, fit = frame_samples(raw, camera, signal=signal, config=config)
    count = samples.size
    if config.cancellation and camera.sensor.gain is None:
        source, offset, floor = _signal_of(raw, camera, signal)
        joint = cancellation_fit(source, offset, floor, camera, config, start=fit)
        if joint is not None and _preferred(fit, joint, config) is joint:
            fit, count = joint, int(joint.bins_n.sum())  # residuals in the joint fit's bins
    return fit, count


def _preferred(fit: LineFit | None, joint: LineFit | None, config: EstimatorConfig) -> LineFit | None:
    """The residual fit ``fit`` or the texture-cancelled one ``joint``.

    Texture biases the residual fit's slope (the gain reads low) but not the joint fit's, which is
    noisier. The joint fit is taken where it tells the gain to within ``config.cancel_max_sigma``
    (relative), unless the two slopes agree within two of its standard deviations (the residual
    fit's own, with what it states for texture, would hide the bias tested for) and the residual fit
    states the smaller uncertainty: then the frame shows no texture bias and the more precise fit
    is kept (a smooth scene). A joint fit less precise than that is still taken
    (``config.cancel_when_biased``) where the residual fit's slope lies more than two of its standard
    deviations above it: the residual fit then shows the bias texture gives it, and the joint fit,
    with its large stated uncertainty, is the honest one (a high gain, whose slope is small, is
    often known only that well: 40 000 e- / 6 DN); and where there is no residual fit at all: the
    prior then weighs what the joint fit tells (:func:`estimate_from_fit`), which beats the defaults."""
    if joint is None or joint.fixed_slope:
        return fit
    if math.sqrt(max(joint.cov[0, 0], 0.0)) > config.cancel_max_sigma * joint.slope:
        if config.cancel_when_biased and (fit is None or (
                not fit.fixed_slope and fit.slope - joint.slope > 2.0 * math.sqrt(max(joint.cov[0, 0], 0.0)))):
            return joint
        return fit
    if fit is not None and not fit.fixed_slope:
        if _no_bias_shown(fit, joint):
            return fit
    return joint


# ----- over a stream ------------------------------------------------------------------------------------


def _strided(size: int, max_samples: int) -> int:
    """Every how many pixels in raster order to sample a frame of ``size`` pixels: at least
    ``size / max_samples``, and prime to 2, 3, 5 and 7 so that every tile phase (every exposure) is
    sampled (a step shared with the tile would keep one exposure only)."""
    need = max(1, int(math.ceil(size / max_samples)))
    return next(k for k in range(need, need + 210) if math.gcd(k, 210) == 1)


def _grouped(signal: np.ndarray, by: np.ndarray) -> np.ndarray:
    """Each sample's group mean of ``signal`` (float64 (N,)), the groups cut from ``by`` (float (N,), DN):
    1 DN wide below 256 DN, 1 % wide above."""
    group = np.where(by < 256.0, np.floor(by), 256.0 + np.floor(np.log(np.maximum(by, 256.0) / 256.0) / np.log(1.01)))
    _, index = np.unique(group, return_inverse=True)
    return (np.bincount(index, weights=signal) / np.bincount(index))[index]


def _clear_of_clipping(by: np.ndarray, floor: float, high: float, model: tuple[float, float]) -> np.ndarray:
    """bool (N,): values ``by`` (DN) four noise standard deviations (under ``model``) clear of both clip levels."""
    slope, intercept = model
    sd = np.sqrt(np.maximum(slope * np.maximum(by, 0.0) + intercept, QUANTISATION_VARIANCE))
    return (by - floor >= 4.0 * sd) & (by + 4.0 * sd < high)


def _difference_samples(a: np.ndarray, b: np.ndarray, k: float, t: np.ndarray) -> NoiseSamples:
    """Samples ``u = (a - k b)^2 / (1 + k^2)`` (float64 (N,), the readings of two frames of a static scene,
    ``k`` their brightness ratio) with their signal coordinates ``t``: ``E[u] = t / g + R``."""
    d = a - k * b
    return NoiseSamples(t=t, u=d * d / (1.0 + k * k))


def temporal_samples(previous: np.ndarray, current: np.ndarray, static: np.ndarray | None, floor: float,
                     high: float, model: tuple[float, float], max_samples: int = 100_000,
                     period: tuple[int, int] | None = None) -> NoiseSamples:
    """Samples from two frames' signals (float (H, W), DN above black) at static pixels.

    ``d = x1 - k x2`` has variance ``(1 + k^2) (s / g + R)`` where the scene did not change (``k``
    removes a global brightness change, flicker), whatever the texture. The pixels are grouped by
    their neighbours one tile (``period``, rows and columns) to the left and right, both frames
    averaged: a value whose noise is independent of the pixel's. Within any group so chosen the
    mean of ``d^2 / (1 + k^2)`` is ``E[s | group] / g + R`` and the mean of ``(x1 + k x2) / 2`` is
    ``E[s | group]``, exactly, for any noise distribution and any texture (the variance is linear in
    the signal). Without a ``period`` (a layout not known: neighbours may have other exposures,
    and groups that mix them follow the signal too loosely to fit a line) the pixels are grouped by
    the pair's own mean, corrected for its noise by :func:`_tweedie`: grouping by a noisy value
    dilutes the slope where pixels crowd the dark end, and the correction, exact only for Gaussian
    noise of one variance, reads a low read noise beside strong shot noise 10-20 % high. A pixel is
    dropped when its pair's mean lies within four noise standard deviations (under ``model``,
    ``(slope, intercept)``) of a clip level, not by either reading: dropping readings
    at 0 or at white truncates their noise (the low read noise the older pair estimate gave with a
    black level of 0), while the mean is independent of the difference (Gaussian noise). Its
    neighbours may clip: they only choose the group.
    """
    h, w = np.shape(previous)
    first, second = np.asarray(previous).ravel(), np.asarray(current).ravel()
    idx = np.arange(0, h * w, _strided(h * w, max_samples))
    a, b = first[idx].astype(np.float64), second[idx].astype(np.float64)
    mask = None if static is None else np.asarray(static, bool).ravel()
    keep = np.ones(a.shape, bool) if mask is None else mask[idx]
    sums = _static_sums([first, second], mask)
    k = sums[0] / sums[1] if sums[1] > 0 else 1.0
    mean = 0.5 * (a + k * b)
    if period is None:
        var_mean = 0.5 * np.maximum(model[0] * np.maximum(mean, 0.0) + model[1], QUANTISATION_VARIANCE)
        signal = _tweedie(mean, var_mean, keep)  # from the density of all pixels, before any cut
        keep &= _clear_of_clipping(mean, floor, high, model)
        if keep.sum() < 100:
            return NoiseSamples(np.zeros(0), np.zeros(0))
        return _difference_samples(a[keep], b[keep], k, signal[keep])
    pw = period[1] if w > period[1] else 1
    x = idx % w
    left, right = x >= pw, x + pw < w
    by = np.zeros(idx.size)
    for side, at in ((left, idx - pw), (right, idx + pw)):  # the neighbours' pair means, where they exist
        j = at[side]
        by[side] += 0.5 * (first[j].astype(np.float64) + k * second[j].astype(np.float64))
    by /= np.maximum(left.astype(np.float64) + right, 1.0)
    keep &= (left | right) & _clear_of_clipping(mean, floor, high, model)
    if keep.sum() < 100:
        return NoiseSamples(np.zeros(0), np.zeros(0))
    return _difference_samples(a[keep], b[keep], k, _grouped(mean[keep], by[keep]))


def _static_sums(frames: list[np.ndarray], static: np.ndarray | None) -> list[float]:
    """The sum of each frame (float (N,), DN) over every static pixel (bool (N,), None: all), float64.

    Their ratios remove a global change of brightness (flicker) from frame differences. Taken over
    the pixels sampled rather than all, a ratio's own noise (about 1 % at 50 000 pixels of a dim frame)
    puts ``(1 - k)^2 s^2`` into every difference: nothing at the dark end, a variance twice the noise's
    at the bright end of a dim frame, where the gain is read (40 000 e- / 6 DN, 7 stops dark: the
    gain 20 % low after 16 runs)."""
    return [float(np.sum(x if static is None else x[static], dtype=np.float64)) for x in frames]


def _tweedie(observed: np.ndarray, variance: np.ndarray, where: np.ndarray, span: float = 400.0) -> np.ndarray:
    """E[true signal | observed], float64 (N,): Tweedie's formula ``x + var * d/dx log p(x)``.

    Binning noise variances by a noisy signal dilutes the slope: where most pixels are dark, those
    observed a little brighter are mostly dark ones with positive noise, so their bin's mean signal
    overstates their true one (and the lowest bin understates). The correction needs only the
    observed density ``p`` (of the pixels ``where``), here a histogram on 1 DN steps over the lowest
    ``span`` DN smoothed by
    2 DN; above that the noise is small against the signal's spread and nothing is changed.
    """
    lo = float(observed[where].min()) if where.any() else 0.0
    edges = np.arange(lo - 8.0, lo + span + 8.0, 1.0)
    counts, _ = np.histogram(observed[where], edges)
    kernel = np.exp(-0.5 * (np.arange(-6, 7) / 2.0) ** 2)
    density = np.convolve(counts.astype(np.float64), kernel / kernel.sum(), mode="same") + 1e-3
    centres = 0.5 * (edges[:-1] + edges[1:])
    score = np.gradient(np.log(density), centres)
    inside = observed < lo + span
    out = observed.astype(np.float64, copy=True)
    out[inside] += variance[inside] * np.interp(observed[inside], centres, score)
    return out


def triple_samples(first: np.ndarray, second: np.ndarray, third: np.ndarray, static: np.ndarray | None,
                   floor: float, high: float, model: tuple[float, float], max_samples: int = 100_000,
                   strata: int = 24) -> NoiseSamples:
    """Samples from three frames' signals (float (H, W), DN above black) at pixels static in all three.

    As :func:`temporal_samples`, but the pixels are grouped by the third frame's own value, whose
    noise is independent of the first two's: the grouping value is the pixel's own light, so the
    groups follow the signal more closely than its neighbours do where the scene has texture.
    Pixels are chosen by ``x3`` alone: dropped within four noise standard deviations of a clip level,
    and at most ``max_samples`` kept, spread over ``strata`` signal strata (equal steps of
    log(x3 + 2 DN), as the fit's bins): a stratum with fewer pixels than its share keeps them all and
    the others share the rest, each sampled evenly (:func:`_stratified`). A frame-wide stride would
    keep one pixel in ten or twenty everywhere, also in the dark strata of a bright scene, where the
    read noise shows and pixels are few. A choice by ``x3`` leaves the samples' expectations exact.
    """
    flat = [np.asarray(x).ravel() for x in (first, second, third)]
    mask = None if static is None else np.asarray(static, bool).ravel()
    sums = _static_sums(flat, mask)
    if min(sums) <= 0:
        return NoiseSamples(np.zeros(0), np.zeros(0))
    k, ratio = sums[0] / sums[1], sums[0] / sums[2]
    candidates = np.arange(flat[2].size) if mask is None else np.flatnonzero(mask)
    candidates, which = _clear_strata(flat[2], candidates, ratio, floor, high, model, strata)
    chosen = _stratified(which, max_samples, strata)
    if chosen.size < 100:
        return NoiseSamples(np.zeros(0), np.zeros(0))
    idx = candidates[chosen]
    a, b, c = (flat[j][idx].astype(np.float64) for j in range(3))
    return _difference_samples(a, b, k, _grouped(0.5 * (a + k * b), c * ratio))


def _clear_strata(third: np.ndarray, candidates: np.ndarray, ratio: float, floor: float, high: float,
                  model: tuple[float, float], strata: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``candidates`` (int64 indices into ``third``, float (N,) DN) whose value times ``ratio`` is clear
    of clipping (:func:`_clear_of_clipping`), and the signal stratum of each (uint8, :func:`_bin_index` over
    them). Readings of whole DN (no response curve) are looked up in a table of their values: the same
    result as computing it for every pixel, at a fraction of the cost."""
    x = third[candidates]
    lo, hi = (float(x.min()), float(x.max())) if x.size else (0.0, 0.0)
    code = x.astype(np.int64) - int(lo) if hi - lo < 2**20 else None
    if code is None or not np.array_equal(code + int(lo), x):  # not whole DN: per pixel
        c = x.astype(np.float64) * ratio
        keep = _clear_of_clipping(c, floor, high, model)
        which = _bin_index(c[keep], strata)[0] if keep.any() else np.zeros(0, np.int64)
        return candidates[keep], which.astype(np.uint8)
    values = (np.arange(code.max() + 1 if code.size else 0) + int(lo)).astype(np.float64) * ratio
    keep = _clear_of_clipping(values, floor, high, model)[code]
    candidates, code = candidates[keep], code[keep]
    present = np.flatnonzero(np.bincount(code, minlength=values.size))
    table = np.zeros(values.size, np.uint8)
    if present.size:
        table[present] = _bin_index(values[present], strata)[0]
    return candidates, table[code]


def _stratified(which: np.ndarray, budget: int, strata: int) -> np.ndarray:
    """At most ``budget`` positions of ``which`` (uint8 (N,), each position's stratum, < ``strata`` <= 255):
    the largest per-stratum quota whose total fits the budget, every stratum with fewer positions keeping
    them all; within a stratum every m-th position in order. int64 (M,), ascending."""
    if which.size <= budget:
        return np.arange(which.size)
    counts = np.bincount(which, minlength=strata)
    ordered = np.sort(counts)
    # water filling: the quota q with sum(min(counts, q)) <= budget
    below = np.concatenate([[0], np.cumsum(ordered)])[:-1]
    above = strata - np.arange(strata)
    j = int(np.count_nonzero(below + ordered * above <= budget))  # the j smallest strata keep all theirs
    quota = max((budget - int(below[j])) // int(above[j]), 1) if j < strata else int(ordered[-1])
    step = np.maximum(-(-counts // quota), 1)
    order = np.argsort(which, kind="stable")  # a radix sort (uint8): each stratum's positions in order
    starts = np.cumsum(counts) - counts
    picks = [np.arange(first, first + n, m) for first, n, m in zip(starts, counts, step) if n]
    return np.sort(order[np.concatenate(picks)])


def pair_fit(previous: np.ndarray, current: np.ndarray, sensor: Sensor, *, floor: float | None = None,
             static: np.ndarray | None = None, config: EstimatorConfig = EstimatorConfig(),
             max_samples: int = 4_000_000, period: tuple[int, int] | None = None
             ) -> tuple[NoiseSamples, LineFit | None]:
    """The noise line from two frames of a static scene (signals above black, float (H, W)).

    Iterated: the clip margins of :func:`temporal_samples` start from twice the default sensor's
    noise (generous) and then follow the fit. ``floor``: the lowest signal a reading can take
    (``-black`` for raw frames). ``period``: the frames' tile (rows, columns), when known: the pixels
    are grouped by neighbours of the same exposure and colour (:func:`temporal_samples`).
    """
    floor = -float(sensor.black_level) if floor is None else floor
    high = _high_level(sensor)
    model = (4.0 / (DEFAULT_FULL_WELL_E / sensor.range_dn),
             4.0 * ((DEFAULT_READ_NOISE_E * sensor.range_dn / DEFAULT_FULL_WELL_E) ** 2 + QUANTISATION_VARIANCE))
    fixed = _fixed(sensor)
    samples, fit = NoiseSamples(np.zeros(0), np.zeros(0)), None
    for _ in range(3):
        samples = temporal_samples(previous, current, static, floor, high, model, max_samples, period)
        fit = fit_line(*bin_samples(samples, config, temporal=True), **fixed,
                       outlier_tolerance=config.outlier_tolerance)
        if fit is None:
            break
        model = (fit.slope, fit.intercept)
    return samples, fit


class NoiseTracker:
    """The noise model of one stream, refined frame by frame.

    Static pixels between consecutive frames give texture-free samples (their difference removes
    the scene); three consecutive frames give them without the pair's correction for binning by a
    noisy signal (:func:`triple_samples`), and are used alone once there are enough of them. Once
    the recent frames hold enough temporal samples (``temporal_enough``) the line is fitted
    to those alone, else to them pooled with the single-frame samples of the recent frames (which
    texture can bias); without any temporal samples (a moving camera, no static mask) that line is
    weighed against the recent frames' texture-cancelled fits (:func:`cancellation_fit`, combined by
    inverse variance) as :func:`estimate_noise` does. A given gain or read noise in the camera is
    kept. Not thread-safe: one per stream.

    :meth:`update` adds a frame and fits; :meth:`add` only adds it, and :meth:`fit` fits what was
    added. The pool is fitted only when what it holds changed, and a fit that adding a frame needs
    (the clip margins of temporal samples, the start of the texture-cancelled fit) is the one
    :meth:`update` would have made after the frame before: ``add, add, update`` gives the estimate
    of ``update, update, update`` to the bit, with a third of the fits where the pool is unchanged
    between runs (the service's runs of three frames once temporal samples suffice).
    """

    def __init__(self, history: int = 16, config: EstimatorConfig = EstimatorConfig(),
                 temporal_samples_per_frame: int = 50_000, temporal_enough: int = 20_000) -> None:
        self.config = config
        self.temporal_per_frame = temporal_samples_per_frame
        self.temporal_enough = temporal_enough
        self._frame_parts: deque[NoiseSamples] = deque(maxlen=history)
        self._temporal_parts: deque[NoiseSamples] = deque(maxlen=history)
        self._joint_fits: deque[LineFit] = deque(maxlen=history)
        self._triple_parts: deque[NoiseSamples] = deque(maxlen=history)
        self._previous: np.ndarray | None = None
        self._before_previous: np.ndarray | None = None  # the frame before it, when it was static to it
        self._previous_static: np.ndarray | None = None  # the mask that related the two
        self._estimate: NoiseEstimate | None = None
        self._camera_key: tuple | None = None
        self._sensor: Sensor | None = None  # of the frames added since the last reset
        self._line_of: tuple[tuple, LineFit | None, int] | None = None  # (pool, its line, samples)
        self._estimate_of: tuple | None = None  # what self._estimate was fitted to

    @property
    def estimate(self) -> NoiseEstimate | None:
        """The estimate of the last fit (:meth:`update` or :meth:`fit`), None before the first."""
        return self._estimate

    def reset(self) -> None:
        """Forget every frame (the camera changed)."""
        self._frame_parts.clear()
        self._temporal_parts.clear()
        self._joint_fits.clear()
        self._triple_parts.clear()
        self._previous = self._before_previous = self._previous_static = None
        self._estimate = None
        self._camera_key = None
        self._sensor = None
        self._line_of = self._estimate_of = None

    def update(self, raw: np.ndarray, camera: Camera, static_mask: np.ndarray | None = None, *,
               signal: np.ndarray | None = None) -> NoiseEstimate:
        """Add one frame (:meth:`add`) and return the refined estimate (:meth:`fit`)."""
        self.add(raw, camera, static_mask, signal=signal)
        return self.fit()

    def add(self, raw: np.ndarray, camera: Camera, static_mask: np.ndarray | None = None, *,
            signal: np.ndarray | None = None) -> None:
        """Add one frame's samples without fitting the pool (but where the samples need the current fit).

        Args:
            raw: uint (H, W) raw frame as delivered.
            camera: its camera; a change of pattern, colour filter, levels or shape starts over.
            static_mask: bool (H, W), pixels known not to have changed since the previous frame (e.g.
                the motion test's static pixels); None gives no temporal samples (a moving camera
                would bias them), only the single-frame ones.
            signal: the linear signal above black when the camera has a response (see :func:`estimate_noise`).
        """
        sensor = camera.sensor
        key = (str(camera.pattern), None if camera.cfa is None else str(camera.cfa), sensor.black_level,
               sensor.white_level, sensor.gain, sensor.read_noise, np.shape(raw))
        if key != self._camera_key:
            self.reset()
            self._camera_key = key
        if sensor.gain is not None and sensor.read_noise is not None:
            self._sensor = sensor
            return
        source, offset, floor = _signal_of(raw, camera, signal)
        sig = np.asarray(source, np.float32) - np.float32(offset)
        static = None if static_mask is None else np.asarray(static_mask, bool)
        if static is not None and static.shape != sig.shape:
            raise SveliveError(f"static mask has shape {static.shape} but the frame {sig.shape}")
        if static is not None and self._previous is not None:
            current = self.fit() if self._sensor is not None else estimate_from_fit(None, sensor, 0)
            model = (1.0 / current.gain, current.read_noise**2 + QUANTISATION_VARIANCE)
            if self._before_previous is not None:
                self._triple_parts.append(triple_samples(self._before_previous, self._previous, sig,
                                                         static & self._previous_static, floor,
                                                         _high_level(sensor), model, self.temporal_per_frame))
            else:
                self._temporal_parts.append(temporal_samples(self._previous, sig, static, floor,
                                                             _high_level(sensor), model, self.temporal_per_frame,
                                                             camera.period))
        self._sensor = sensor
        config = self.config
        temporal = self._temporal()
        if temporal.size < self.temporal_enough:
            samples, _ = frame_samples(raw, camera, signal=sig, config=config)
            self._frame_parts.append(samples)
        # temporal samples are texture-free: with any, the pooled line is the better evidence
        if config.cancellation and sensor.gain is None and temporal.size == 0:
            frame_joint = cancellation_fit(sig, 0.0, floor, camera, config, start=self._line()[0])
            if frame_joint is not None:
                self._joint_fits.append(frame_joint)
        if static is not None and self._previous is not None:
            self._before_previous, self._previous_static = self._previous, static
        else:
            self._before_previous = self._previous_static = None
        self._previous = np.array(sig, copy=True)

    def fit(self) -> NoiseEstimate:
        """The estimate from every frame added (refitted only when the pool changed since the last fit)."""
        sensor = self._sensor
        if sensor is None:
            raise SveliveError("no frame added to the noise tracker")
        if sensor.gain is not None and sensor.read_noise is not None:
            self._estimate = NoiseEstimate.given(sensor)
            return self._estimate
        config = self.config
        with_joint = config.cancellation and sensor.gain is None and self._temporal().size == 0
        pool, joints = self._pool()[0], tuple(self._joint_fits) if with_joint else ()
        if self._estimate_of is not None and _same(self._estimate_of, (pool, joints)):
            return self._estimate
        fit, count = self._line()
        joint = _combined(list(joints)) if with_joint else None
        if joint is not None and _preferred(fit, joint, config) is joint:
            fit, count = joint, int(joint.bins_n.sum())
        self._estimate = estimate_from_fit(fit, sensor, count)
        self._estimate_of = (pool, joints)
        return self._estimate

    def _temporal(self) -> NoiseSamples:
        """The temporal samples the pool holds: three frames' alone once enough, else with the pairs'."""
        return NoiseSamples.join(self._temporal_list())

    def _temporal_list(self) -> list[NoiseSamples]:
        triples = list(self._triple_parts)
        if sum(p.size for p in triples) >= self.temporal_enough:
            return triples
        return [*triples, *self._temporal_parts]

    def _pool(self) -> tuple[tuple[NoiseSamples, ...], bool]:
        """The parts the line is fitted to, and whether they are temporal alone (binned as such)."""
        temporal = self._temporal_list()
        if sum(p.size for p in temporal) >= self.temporal_enough:
            return tuple(temporal), True
        return (*self._frame_parts, *temporal), False

    def _line(self) -> tuple[LineFit | None, int]:
        """The line fitted to the pool and its sample count, fitted again only when the pool changed."""
        parts, only_temporal = self._pool()
        if self._line_of is not None and _same(self._line_of[0], (parts, only_temporal)):
            return self._line_of[1], self._line_of[2]
        pooled = NoiseSamples.join(list(parts))
        fit = fit_line(*bin_samples(pooled, self.config, temporal=only_temporal), **_fixed(self._sensor),
                       outlier_tolerance=self.config.outlier_tolerance)
        self._line_of = ((parts, only_temporal), fit, pooled.size)
        return fit, pooled.size


def _same(a: object, b: object) -> bool:
    """Whether two nests of tuples hold the very same objects (identity, not equality: arrays)."""
    if isinstance(a, tuple) and isinstance(b, tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return a is b


def _combined(fits: list[LineFit]) -> LineFit | None:
    """Texture-cancelled fits of several frames as one: slope and intercept weighted by the inverse of
    their variances, the covariance that of the weighted mean (the frames' noise is independent; the
    texture the fits removed is not, and is no part of their covariance). None for no fits."""
    if not fits:
        return None
    if len(fits) == 1:
        return fits[0]
    out = []
    for k in (0, 1):
        var = np.array([max(f.cov[k, k], 1e-300) for f in fits])
        values = np.array([(f.slope, f.intercept)[k] for f in fits])
        w = 1.0 / var
        out.append((float(np.sum(w * values) / np.sum(w)), 1.0 / float(np.sum(w))))
    first = fits[0]
    return replace(first, slope=out[0][0], intercept=out[1][0], cov=np.diag([out[0][1], out[1][1]]),
                   bins_n=np.concatenate([f.bins_n for f in fits]), bins_t=np.concatenate([f.bins_t for f in fits]),
                   bins_v=np.concatenate([f.bins_v for f in fits]),
                   inlier=np.concatenate([f.inlier for f in fits]))


# ----- one stream's model: what svelive.Reconstructor, stream_noise and reprocessing share ---------------


def variance_uncertainty(estimate: NoiseEstimate) -> float:
    """The largest relative standard uncertainty of the modelled variance ``v(t) = t / g + r^2 + 1/12`` over
    every signal ``t >= 0`` (DN), a float >= 0; ``inf`` when an uncertainty is unknown.

    With independent errors ``sd(v) = sqrt((t sd(g) / g^2)^2 + (2 r sd(r))^2)``, and since
    ``sqrt(a^2 + b^2) <= a + b``, ``sd(v) / v <= max(sd(g) / g, 2 r sd(r) / (r^2 + 1/12))``: the
    shot end's and the dark end's relative uncertainties, whichever is larger.
    """
    if estimate.gain_sigma is None or estimate.read_noise_sigma is None:
        return math.inf
    shot = estimate.gain_sigma / max(estimate.gain, 1e-12)
    dark = 2.0 * estimate.read_noise * estimate.read_noise_sigma / (estimate.read_noise**2 + QUANTISATION_VARIANCE)
    value = max(shot, dark)
    return value if math.isfinite(value) else math.inf


def agree(a: NoiseEstimate, b: NoiseEstimate, sigmas: float = 3.0) -> bool:
    """Whether two estimates of one sensor agree: gain and read noise each within ``sigmas`` combined
    standard uncertainties (an unknown uncertainty agrees with anything)."""
    for x, y, sx, sy in ((a.gain, b.gain, a.gain_sigma, b.gain_sigma),
                         (a.read_noise, b.read_noise, a.read_noise_sigma, b.read_noise_sigma)):
        if sx is None or sy is None:
            continue
        if abs(x - y) > sigmas * math.hypot(sx, sy):
            return False
    return True


@dataclass(frozen=True)
class NoiseSchedule:
    """When a stream refines its noise model, and when the model is trusted (:class:`StreamNoise`).

    Attributes:
        run_frames: consecutive frames per run of the tracker (3: the first frame's single-frame
            samples, then the static pixels' differences over the next two, as the service's runs).
        refit_every: frames from the start of one run to the start of the next; 0 stops after the
            first complete run. The tracker is fitted after the second and the last frame of the
            first run, then once per run (about 250 ms CPU per fit at 1920x1200). While the model is
            not trusted the runs come sooner: 0, 3, 9, 21, ... frames apart (StreamNoise).
        trusted_below: the model is trusted (fusion may change the output) once a fit with temporal
            samples states the modelled variance to within this relative standard uncertainty at
            every signal (:func:`variance_uncertainty`). At 0.15 a variance one standard uncertainty
            low leaves the fusion's 3-sigma detail test at 3 sqrt(0.85) = 2.77 sigma and its 4-sigma
            motion test at 3.7 sigma: the share of noise taken for detail or motion at most doubles
            (0.27 % -> 0.56 %, 6e-5 -> 2e-4), where the fixed defaults can be several times off.
    """

    run_frames: int = 3
    refit_every: int = 64
    trusted_below: float = 0.15

    def __post_init__(self) -> None:
        if int(self.run_frames) < 2:
            raise SveliveError(f"noise schedule: run_frames must be >= 2, got {self.run_frames}")
        if int(self.refit_every) != 0 and int(self.refit_every) < int(self.run_frames):
            raise SveliveError(f"noise schedule: refit_every must be 0 or >= run_frames, got {self.refit_every}")
        if not self.trusted_below > 0:
            raise SveliveError(f"noise schedule: trusted_below must be > 0, got {self.trusted_below}")


class StreamNoise:
    """The noise model of one stream whose camera does not give its gain or read noise, refined as frames come.

    The first frame gives the single-frame estimate (:func:`estimate_noise`, what
    ``svelive.reconstruct`` uses); then runs of ``schedule.run_frames`` consecutive frames, with the
    pixels the motion tests found static, feed a :class:`NoiseTracker` (as the live service's noise
    stage does), fitted after the first run's second and last frames, then once per run, a run
    starting every ``schedule.refit_every`` frames. A run broken by a frame of unknown motion (a
    reset, a cut) is dropped; before the first complete run the next frame starts another. The first
    run's last fit replaces the fit after its second frame whatever it says (it holds that fit's samples
    and the three frames'); a later run's fit that disagrees with the model (:func:`agree`) keeps the
    model but distrusts it until a fit agrees. A given gain or read noise is kept. Not thread-safe: one
    caller at a time, frames in order.
    """

    def __init__(self, schedule: NoiseSchedule = NoiseSchedule(), tracker: NoiseTracker | None = None) -> None:
        self.schedule = schedule
        self.tracker = tracker if tracker is not None else NoiseTracker()
        self.fits = 0  # tracker fits so far
        self._estimate: NoiseEstimate | None = None
        self._fitted = False  # whether _estimate is a fit with temporal samples (not the first frame's)
        self._position: int | None = None  # the last frame fed's place in its run, None between runs
        self._runs = 0  # complete runs
        self._wait = 0  # frames before the next run starts
        self._untrusted_runs = 0  # complete runs in a row after which the model was not trusted
        self._conflict = False  # whether the tracker's last fit contradicted the model in use

    @property
    def estimate(self) -> NoiseEstimate | None:
        """The model in use, None before the first frame."""
        return self._estimate

    @property
    def trusted(self) -> bool:
        """Whether the model is known well enough for fusion (``schedule.trusted_below``): given, or a
        tracker's fit with temporal samples that states it that well. The first frame's estimate never is."""
        estimate = self._estimate
        if estimate is None:
            return False
        if estimate.source == "given":
            return True
        return self._fitted and not self._conflict and variance_uncertainty(estimate) <= self.schedule.trusted_below

    def first(self, raw: np.ndarray, camera: Camera, *, signal: np.ndarray | None = None) -> NoiseEstimate:
        """The model for a frame when there is none yet: the frame's own (:func:`estimate_noise`, as a
        single frame is reconstructed), kept until the tracker's first fit."""
        if self._estimate is None:
            self._estimate = estimate_noise(raw, camera, signal=signal)
        return self._estimate

    def needs_static(self) -> bool:
        """Whether :meth:`observe` reads the next frame's static mask (the frame continues a run; a frame
        that starts one or waits between runs gives no temporal samples), so a caller makes it only then."""
        return self._position is not None

    def observe(self, raw: np.ndarray, camera: Camera, static: np.ndarray | None, *,
                signal: np.ndarray | None = None) -> NoiseEstimate | None:
        """Feed the stream's next frame, on the schedule (the tracker reads only the frames of its runs).

        Args:
            raw: uint (H, W), the frame as delivered; camera: its camera (without an estimated model).
            static: bool (H, W), the pixels found static against the previous frame given here, or
                None where that is unknown (the first frame, after a reset or a lost frame).
            signal: the linear signal above black for a camera with a response curve.
        Returns:
            The new model when the tracker was fitted after this frame, else None.
        """
        schedule = self.schedule
        if self._position is not None and static is None:  # the run is broken: drop it
            self._position = None
        if self._position is None:
            if self._runs > 0 and (self._wait > 0 or schedule.refit_every <= 0):
                self._wait -= 1
                return None
            self._position = 0
            static = None
        else:
            self._position += 1
        self.tracker.add(raw, camera, static, signal=signal)
        last = self._position == schedule.run_frames - 1
        if last:
            self._position = None
            self._runs += 1
        elif not (self._runs == 0 and self._position >= 1):
            return None
        fit = self.tracker.fit()
        self.fits += 1
        taken = self._take(fit)
        if last:
            self._wait = self._next_wait()
        return taken

    def _next_wait(self) -> int:
        """Frames between the run just complete and the next: the schedule's once the model is trusted; while it
        is not (the stream's output is then its single frames), 0, 3, 9, 21, 45, ... frames (the gaps doubling
        up to the schedule's), so that a model the first run could not state well enough (a small or busy frame)
        is refined within a few runs at a bounded cost: about log2(refit_every / run_frames) runs more."""
        schedule = self.schedule
        full = max(schedule.refit_every - schedule.run_frames, 0)
        if self.trusted:
            self._untrusted_runs = 0
            return full
        self._untrusted_runs += 1
        return min(full, schedule.run_frames * (2 ** (self._untrusted_runs - 1) - 1))

    def _take(self, fit: NoiseEstimate) -> NoiseEstimate | None:
        """The model after a tracker's fit (see the class): the fit, or None where the model in use is kept."""
        if fit.source == "default":  # the frames told nothing (no unclipped flat or static pixels): keep the model
            return None
        if self._fitted and self._runs > 1 and not agree(fit, self._estimate):
            # two fits of one sensor that their stated uncertainties cannot reconcile: something the motion
            # masks missed (or texture) is in the samples; keep the model in use, and distrust it until a fit agrees.
            # Not within the first run: its last fit holds every sample of the one before and the three frames'
            # (unbiased) samples, where the fit after two frames has only a pair's, which can be confidently
            # wrong (BrightRings 3 000 e- / 2 e-, 4 stops under: gain 2.2x stated 14 %, then 1.0x from three)
            self._conflict = True
            return None
        self._estimate, self._fitted, self._conflict = fit, True, False
        return self._estimate
