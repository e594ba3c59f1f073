"""One frame's noise estimate (:func:`estimate_from_frame`, :func:`frame_fit`): residuals against more exposed
neighbours at flat places, and the choice between their line and the texture-cancelled one.

In an SVE frame the same radiance is seen
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

Texture that passes the flatness tests is a fraction of the noise they test against, so it grows with
the signal like shot noise and the bins' scatter cannot show it: the slope's shift under a stricter
selection and under a texture term ``k t^2`` is added to its variance when significant. Where the
texture-cancelled fit (svelive/noise/cancellation.py) tells the gain to within 50 % and disagrees with
the residual fit beyond its noise, :func:`estimate_from_frame` takes it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from svelive.core.sensor import Sensor
from svelive.noise.cancellation import _no_bias_shown, cancellation_fit
from svelive.noise.inputs import _block_lines, _fixed, _high_level, _layout, _signal_of
from svelive.noise.model import QUANTISATION_VARIANCE, EstimatorConfig, LineFit, NoiseEstimate, NoiseSamples
from svelive.noise.prior import PRIOR_LOG_SIGMA, estimate_from_fit
from svelive.noise.stats import _bin_index, bin_samples, chi2_quantile, chi2_quantile_array, fit_line

if TYPE_CHECKING:  # the Camera is only read here (its pattern, colour filter and sensor)
    from svelive.core.camera import Camera


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
                              chi2_quantile_array(config.region_quantile, others)))
    return out


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
            sel = (keep & (spread <= chi2_quantile(strict.flat_quantile, dof))
                   & (region_sum <= chi2_quantile_array(strict.region_quantile, others)))
            stricter = NoiseSamples(t=t[sel], u=u[sel])
        keep &= spread <= chi2_quantile(config.flat_quantile, dof)
        keep &= region_sum <= data.region_limit
    return (NoiseSamples(t=t[keep], u=u[keep]), (spread / dof * region_sum / np.maximum(others, 1))[keep],
            stricter)


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


def estimate_from_frame(raw: np.ndarray, camera: Camera, *, signal: np.ndarray | None = None,
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
    """The noise line :func:`estimate_from_frame` takes from one frame and the samples behind it: the
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
