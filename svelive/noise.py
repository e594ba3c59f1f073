"""The noise model from the data: gain (electrons per DN) and read noise (DN) of a sensor, from its frames.

The model is the sensor's (svelive/sensor.py): a reading with expected signal
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

Over a stream (:class:`NoiseTracker`): the difference of two consecutive frames
at static pixels removes the scene altogether (variance ``2 (s / g + R)``); those
samples are pooled with every frame's single-frame samples, over a bounded
history, and the line is refitted.

The uncertainty is the weighted fit's covariance (bins weighted by the variance
of a variance estimate, ``2 v^2 / n``), scaled up by the reduced chi-square when
the bins scatter more than that.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from svelive.errors import SveliveError
from svelive.sensor import DEFAULT_FULL_WELL_E, DEFAULT_READ_NOISE_E, Sensor

if TYPE_CHECKING:  # the Camera is only read here (its pattern, colour filter and sensor)
    from svelive.camera import Camera

#: Variance of uniform quantisation to integers, DN^2.
QUANTISATION_VARIANCE = 1.0 / 12.0


@dataclass(frozen=True)
class EstimatorConfig:
    """Knobs of the single-frame estimator (the defaults are the documented method).

    Attributes:
        max_samples: pixel pairs used at most (a strided subset of the frame beyond that).
        texture_fraction: a place is flat when the guide's spread beyond its own noise is
            below this fraction of the measured pixel's noise variance.
        guide_noise_factor: allowance for the guide's own noise, in units of its expected variance.
        clip_sigma: per-bin clipping of residuals, in standard deviations.
        bins: signal bins at most.
        min_bin: samples per bin at least.
        outlier_tolerance: a bin more than this fraction (plus 3 standard errors) above the line is dropped.
        iterations: passes of select-fit after the first, model-free one.
        reach: farthest partner, pixels (Chebyshev distance).
        start_fraction: the first pass keeps this flattest fraction of every signal bin.
    """

    max_samples: int = 150_000
    texture_fraction: float = 0.05
    guide_noise_factor: float = 1.5
    clip_sigma: float = 3.0
    bins: int = 24
    min_bin: int = 150
    outlier_tolerance: float = 0.1
    iterations: int = 3
    reach: int = 2
    start_fraction: float = 0.25


@dataclass(frozen=True)
class NoiseEstimate:
    """A sensor noise model and how well it is known.

    Attributes:
        gain: electrons per DN.
        read_noise: read noise, DN (standard deviation, quantisation excluded).
        gain_sigma: standard uncertainty of ``gain`` (e-/DN); 0 when given, None when unknown.
        read_noise_sigma: standard uncertainty of ``read_noise`` (DN); 0 when given, None when unknown.
        samples: noise samples (pixel pairs) the estimate rests on.
        source: "given" (both from the user or datasheet), "estimated" (from the data,
            a given value kept), "default" (the data could not tell; the sensor defaults).
    """

    gain: float
    read_noise: float
    gain_sigma: float | None
    read_noise_sigma: float | None
    samples: int
    source: str

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

    def variance(self, t: np.ndarray | float) -> np.ndarray | float:
        return np.maximum(self.slope * np.asarray(t) + self.intercept, QUANTISATION_VARIANCE)


# ----- pair samples from one frame ------------------------------------------------------------------


def _partners(tile_e: np.ndarray, tile_c: np.ndarray | None, reach: int) -> list[tuple[int, int, int, int]]:
    """For every phase (a, b) of the joint tile, the offset (dy, dx) of its partner: the pixel of the same
    colour and the highest exposure above its own among its 8 neighbours, else within ``reach``.
    Phases without one (the highest exposure) are left out. Returns [(a, b, dy, dx), ...]."""
    ph, pw = tile_e.shape
    out = []
    for a in range(ph):
        for b in range(pw):
            best = None
            for dy in range(-reach, reach + 1):
                for dx in range(-reach, reach + 1):
                    qa, qb = (a + dy) % ph, (b + dx) % pw
                    if (dy, dx) == (0, 0) or tile_e[qa, qb] <= tile_e[a, b] * 1.01:
                        continue
                    if tile_c is not None and tile_c[qa, qb] != tile_c[a, b]:
                        continue
                    # the 8-neighbourhood first, then the highest exposure (the most precise guide), then the nearest
                    key = (max(abs(dy), abs(dx)), -tile_e[qa, qb], dy * dy + dx * dx, abs(dy), dy, dx)
                    if best is None or key < best:
                        best = key
            if best is not None:
                out.append((a, b, best[4], best[5]))
    return out


@dataclass(frozen=True)
class _PairData:
    """Raw material of the pair samples, gathered once and re-selected at every iteration (float64 (N,))."""

    xp: np.ndarray
    xq: np.ndarray
    rho: np.ndarray
    guide_var: np.ndarray  # sample variance of the four guide readings, in q's units (DN^2)


def _gather_pairs(signal: np.ndarray, exposure: np.ndarray, tile_e: np.ndarray, tile_c: np.ndarray | None, high: float, config: EstimatorConfig) -> _PairData:
    """Pairs (p, partner q) and q's four lattice neighbours over a strided subset of whole tiles.

    ``high``: signal (DN) at or above which a reading may be clipped; pairs touching it are dropped.
    """
    ph, pw = tile_e.shape
    h, w = signal.shape
    ny, nx = h // ph, w // pw
    empty = _PairData(*(np.zeros(0) for _ in range(4)))
    partners = _partners(tile_e, tile_c, config.reach)
    if ny < 4 or nx < 4 or not partners:
        return empty
    x4 = signal[:ny * ph, :nx * pw].reshape(ny, ph, nx, pw)
    e4 = exposure[:ny * ph, :nx * pw].reshape(ny, ph, nx, pw)
    per_phase = config.max_samples / len(partners)
    stride = max(1, int(math.ceil(math.sqrt(ny * nx / per_phase))))
    parts = []
    for a, b, dy, dx in partners:
        ti, qa = divmod(a + dy, ph)
        tj, qb = divmod(b + dx, pw)
        # tile rows i with i + ti - 1 >= 0 and i + ti + 1 <= ny - 1 (the guide's neighbours exist)
        i0, i1 = max(0, 1 - ti), min(ny, ny - 1 - ti)
        j0, j1 = max(0, 1 - tj), min(nx, nx - 1 - tj)
        if i1 <= i0 or j1 <= j0:
            continue
        rows, cols = slice(i0, i1, stride), slice(j0, j1, stride)

        def at(di: int, dj: int, pa: int, pb: int, arr: np.ndarray = x4) -> np.ndarray:
            return arr[i0 + di:i1 + di:stride, pa, j0 + dj:j1 + dj:stride, pb]

        xp = x4[rows, a, cols, b]
        xq = at(ti, tj, qa, qb)
        guide = np.stack([at(ti - 1, tj, qa, qb), at(ti + 1, tj, qa, qb),
                          at(ti, tj - 1, qa, qb), at(ti, tj + 1, qa, qb)])
        rho = e4[rows, a, cols, b] / at(ti, tj, qa, qb, e4)
        ok = (xq < high) & (guide.max(axis=0) < high) & (xp < high)
        parts.append((xp[ok], xq[ok], rho[ok], guide.var(axis=0, ddof=1)[ok]))
    if not parts:
        return empty
    return _PairData(*(np.concatenate([p[k] for p in parts]).astype(np.float64) for k in range(4)))


def _select_pairs(data: _PairData, model: LineFit | tuple[float, float] | None, floor: float, high: float,
                  config: EstimatorConfig) -> NoiseSamples:
    """Pair samples at flat, unclipped places under the current model ``(slope, intercept)``.

    Without a model (the first pass), the clip margins take the guide's spread as the noise scale
    and the flat places are the flattest ``start_fraction`` of each signal bin, by the guide's spread
    in ``p``'s units: a ranking that needs no noise model and, not seeing ``p`` or ``q``, no bias.
    """
    rho = data.rho
    s_p = rho * data.xq  # p's signal, told by its partner
    spread_p = data.guide_var * rho * rho  # the guide's spread in p's units (noise and texture)
    if model is None:
        sd_p = np.sqrt(np.maximum(spread_p, QUANTISATION_VARIANCE))
        keep = (s_p - floor >= 4.0 * sd_p) & (s_p + 4.0 * sd_p < high)
        keep &= _flattest_per_bin(s_p, spread_p, keep, config)
    else:
        slope, intercept = (model.slope, model.intercept) if isinstance(model, LineFit) else model
        var_p = np.maximum(slope * np.maximum(s_p, 0) + intercept, QUANTISATION_VARIANCE)
        var_q = np.maximum(slope * np.maximum(data.xq, 0) + intercept, QUANTISATION_VARIANCE)
        sd_p = np.sqrt(var_p)
        keep = (s_p - floor >= 4.0 * sd_p) & (s_p + 4.0 * sd_p < high)
        keep &= spread_p <= config.guide_noise_factor * var_q * rho * rho + config.texture_fraction * var_p
    rho, s_p = rho[keep], s_p[keep]
    r = data.xp[keep] - s_p
    norm = 1.0 + rho * rho
    return NoiseSamples(t=s_p * (1.0 + rho) / norm, u=r * r / norm)


def _flattest_per_bin(s: np.ndarray, spread: np.ndarray, keep: np.ndarray, config: EstimatorConfig) -> np.ndarray:
    """bool (N,): among ``keep``, the samples whose ``spread`` is within the lowest ``start_fraction``
    of their bin of ``s`` (equal-count bins, as the fit's)."""
    out = np.zeros(s.size, bool)
    idx = np.flatnonzero(keep)
    nb = min(config.bins, idx.size // config.min_bin)
    if nb < 1:
        return out
    order = idx[np.argsort(s[idx], kind="stable")]
    edges = np.linspace(0, order.size, nb + 1).astype(np.int64)
    for lo, hi in zip(edges[:-1], edges[1:]):
        members = order[lo:hi]
        limit = np.quantile(spread[members], config.start_fraction)
        out[members[spread[members] <= limit]] = True
    return out


# ----- robust statistics and the line fit -------------------------------------------------------------


def _clip_correction(k: float) -> float:
    """E[z^2 | |z| < k] for a standard normal z: the factor a k-sigma clipped mean square falls short by."""
    phi = math.exp(-0.5 * k * k) / math.sqrt(2 * math.pi)
    inside = math.erf(k / math.sqrt(2))
    return 1.0 - 2.0 * k * phi / inside


def _robust_variance(u: np.ndarray, clip_sigma: float) -> tuple[float, int]:
    """Variance from squared residuals ``u`` (chi-square with one degree of freedom times sigma^2, plus
    outliers): the clipped mean at ``clip_sigma`` iterated from the median, corrected for the clip."""
    v = float(np.median(u)) / 0.4549  # median of chi-square_1
    corr = _clip_correction(clip_sigma)
    kept = u
    for _ in range(4):
        if not v > 0:
            v = float(np.mean(u)) if u.size else 0.0
            break
        kept = u[u <= clip_sigma * clip_sigma * v]
        if kept.size == 0:
            break
        v = float(np.mean(kept)) / corr
    return v, int(kept.size)


def bin_samples(samples: NoiseSamples, config: EstimatorConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Equal-count signal bins: (mean t, robust variance, count), float64/float64/int64 (B,)."""
    n = samples.size
    nb = min(config.bins, n // config.min_bin)
    if nb < 1:
        return np.zeros(0), np.zeros(0), np.zeros(0, np.int64)
    order = np.argsort(samples.t, kind="stable")
    edges = np.linspace(0, n, nb + 1).astype(np.int64)
    t, v, c = np.empty(nb), np.empty(nb), np.empty(nb, np.int64)
    for k, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
        idx = order[lo:hi]
        t[k] = float(np.mean(samples.t[idx]))
        v[k], c[k] = _robust_variance(samples.u[idx], config.clip_sigma)
    return t, v, c


def fit_line(t: np.ndarray, v: np.ndarray, n: np.ndarray, *, slope: float | None = None,
             intercept: float | None = None, outlier_tolerance: float = 0.1) -> LineFit | None:
    """Weighted least squares of ``v = slope * t + intercept`` over bins, dropping bins well above the line.

    Each bin weighs ``n / (2 model^2)`` (a variance estimate's variance is ``2 v^2 / n``). A bin
    more than ``outlier_tolerance`` plus three standard errors above the line is dropped (texture only
    inflates); one far below (four standard errors and the tolerance) too. A given ``slope`` or
    ``intercept`` is held fixed. None when fewer than 2 bins (3 for both free) remain or the slope is not positive.
    """
    t, v, n = (np.asarray(a, np.float64) for a in (t, v, n))
    free = [slope is None, intercept is None]
    need = 1 + sum(free)
    if t.size < need:
        return None
    inlier = np.ones(t.size, bool)
    model = np.maximum(v, QUANTISATION_VARIANCE)
    coef = np.array([slope or 0.0, intercept or 0.0])
    cov = np.zeros((2, 2))
    for _ in range(10):
        w = np.sqrt(n / 2.0) / model * inlier
        target = v - (0.0 if slope is None else slope * t) - (0.0 if intercept is None else intercept)
        cols = [c for c, f in zip((t, np.ones_like(t)), free) if f]
        a = np.stack(cols, axis=1)
        if int(inlier.sum()) < need:
            return None
        sol, *_ = np.linalg.lstsq(a * w[:, None], target * w, rcond=None)
        coef = np.array([sol[0] if free[0] else slope, sol[-1] if free[1] else intercept], np.float64)
        model_new = np.maximum(coef[0] * t + coef[1], QUANTISATION_VARIANCE)
        se = model_new * np.sqrt(2.0 / n)
        new_inlier = ((v <= model_new * (1 + outlier_tolerance) + 3 * se)
                      & (v >= model_new * (1 - outlier_tolerance) - 4 * se))
        converged = np.array_equal(new_inlier, inlier) and np.allclose(model_new, model, rtol=1e-4)
        model, inlier = model_new, new_inlier
        if converged:
            break
        if int(inlier.sum()) < need:
            return None
    w = np.sqrt(n / 2.0) / model * inlier
    cols = [c for c, f in zip((t, np.ones_like(t)), free) if f]
    a = np.stack(cols, axis=1) * w[:, None]
    dof = max(int(inlier.sum()) - need, 1)
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
    return LineFit(float(coef[0]), float(coef[1]), cov, t, v, n.astype(np.int64), inlier)


def estimate_from_fit(fit: LineFit | None, sensor: Sensor, samples: int) -> NoiseEstimate:
    """The NoiseEstimate of a fitted line, the sensor's given values kept, the defaults where the fit failed."""
    given_gain, given_read = sensor.gain, sensor.read_noise
    if given_gain is not None and given_read is not None:
        return NoiseEstimate(given_gain, given_read, 0.0, 0.0, samples, "given")
    if fit is None:
        gain = given_gain if given_gain is not None else DEFAULT_FULL_WELL_E / sensor.range_dn
        read = given_read if given_read is not None else DEFAULT_READ_NOISE_E / gain
        return NoiseEstimate(gain, read, None if given_gain is None else 0.0,
                             None if given_read is None else 0.0, samples, "default")
    gain = 1.0 / fit.slope
    gain_sigma = math.sqrt(max(fit.cov[0, 0], 0.0)) * gain * gain
    read_var = fit.intercept - QUANTISATION_VARIANCE
    read = math.sqrt(max(read_var, 0.0))
    sd_r = math.sqrt(max(fit.cov[1, 1], 0.0))
    read_sigma = sd_r / (2 * read) if read > math.sqrt(sd_r) else math.sqrt(sd_r)
    return NoiseEstimate(gain if given_gain is None else given_gain, read if given_read is None else given_read,
                         gain_sigma if given_gain is None else 0.0, read_sigma if given_read is None else 0.0,
                         samples, "estimated")


# ----- the public single-frame estimate ---------------------------------------------------------------


def _layout(camera: Camera, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The exposure of every pixel (H, W), and the joint tile's nominal exposures and channels (ph, pw)."""
    pattern = camera.require_pattern()
    period = camera.period
    reps = lambda tile: np.tile(tile, (period[0] // tile.shape[0], period[1] // tile.shape[1]))  # noqa: E731
    tile_e = reps(np.asarray(pattern.tile, np.float64))
    tile_c = None if camera.cfa is None else reps(np.asarray(camera.cfa.tile))
    return pattern.exposure_map(shape), tile_e, tile_c


def _signal_of(raw: np.ndarray, camera: Camera, signal: np.ndarray | None) -> tuple[np.ndarray, float]:
    """Linear signal above black (float32 (H, W)) and the lowest value it can take (DN)."""
    sensor = camera.sensor
    raw = camera.check(raw)
    if signal is not None:
        signal = np.asarray(signal, np.float32)
        if signal.shape != raw.shape:
            raise SveliveError(f"signal has shape {signal.shape} but the raw frame {raw.shape}")
        # a response's linearisation clips at black; raw frames clip at raw 0
        return signal, 0.0 if camera.response is not None else -float(sensor.black_level)
    if camera.response is not None:
        raise SveliveError("this camera has a response curve: give the linearised signal "
                           "(signal=svelive.reconstruction.input.prepare(raw, camera).signal)")
    out = raw.astype(np.float32)
    out -= np.float32(sensor.black_level)
    return out, -float(sensor.black_level)


def _high_level(sensor: Sensor) -> float:
    """Signal (DN) from which a reading may be clipped at white: two percent below the range."""
    return 0.98 * sensor.range_dn


def frame_samples(raw: np.ndarray, camera: Camera, *, signal: np.ndarray | None = None,
                  config: EstimatorConfig = EstimatorConfig()) -> tuple[NoiseSamples, LineFit | None]:
    """The single-frame estimator's flat-place samples of one frame and the line fitted to them."""
    sig, floor = _signal_of(raw, camera, signal)
    exposure, tile_e, tile_c = _layout(camera, sig.shape)
    high = _high_level(camera.sensor)
    data = _gather_pairs(sig, exposure, tile_e, tile_c, high, config)
    if data.xp.size < 3 * config.min_bin:
        return NoiseSamples(np.zeros(0), np.zeros(0)), None
    fixed = _fixed(camera.sensor)
    model: LineFit | None = None
    fit, samples = None, NoiseSamples(np.zeros(0), np.zeros(0))
    for _ in range(1 + config.iterations):
        samples = _select_pairs(data, model, floor, high, config)
        fit = fit_line(*bin_samples(samples, config), **fixed, outlier_tolerance=config.outlier_tolerance)
        if fit is None:
            break
        model = fit
    return samples, fit


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
        return NoiseEstimate(sensor.gain, sensor.read_noise, 0.0, 0.0, 0, "given")
    samples, fit = frame_samples(raw, camera, signal=signal, config=config)
    return estimate_from_fit(fit, sensor, samples.size)


# ----- over a stream ------------------------------------------------------------------------------------


def temporal_samples(previous: np.ndarray, current: np.ndarray, static: np.ndarray | None, floor: float,
                     high: float, max_samples: int = 100_000) -> NoiseSamples:
    """Samples from two frames' signals (float (H, W), DN above black) at static pixels.

    ``x1 - x2`` has variance ``2 (s / g + R)`` where the scene did not change; binned by the
    pair's mean (for a Gaussian pair the mean and the difference are independent, so binning by it
    does not bias). Pixels whose mean is within four floor-noise steps of either clip level are
    dropped by that mean, not by either reading. A global brightness change (flicker) is removed first.
    """
    a = np.asarray(previous, np.float64)
    b = np.asarray(current, np.float64)
    step = max(1, int(math.ceil(math.sqrt(a.size / max_samples))))
    a, b = a[::step, ::step], b[::step, ::step]
    keep = np.ones(a.shape, bool) if static is None else np.asarray(static, bool)[::step, ::step]
    mean = 0.5 * (a + b)
    keep &= (mean - floor >= 8.0) & (mean < high - 8.0 * np.sqrt(np.maximum(mean, 1.0)) / 4 - 8.0)
    if keep.sum() < 100:
        return NoiseSamples(np.zeros(0), np.zeros(0))
    sa, sb = a[keep], b[keep]
    k = float(sa.sum() / sb.sum()) if sb.sum() > 0 else 1.0
    d = sa - k * sb
    norm = 1.0 + k * k
    return NoiseSamples(t=0.5 * (sa + k * sb), u=d * d / norm)


class NoiseTracker:
    """The noise model of one stream, refined frame by frame.

    Holds the flat-place pair samples of the last ``history`` frames and the temporal-difference
    samples of static pixels between consecutive frames, and refits the line over all of them.
    A given gain or read noise in the camera is kept. Not thread-safe: one per stream.
    """

    def __init__(self, history: int = 16, config: EstimatorConfig = EstimatorConfig(),
                 temporal_samples_per_frame: int = 50_000) -> None:
        self.config = config
        self.temporal_per_frame = temporal_samples_per_frame
        self._parts: deque[NoiseSamples] = deque(maxlen=2 * history)
        self._previous: tuple[np.ndarray, tuple] | None = None
        self._estimate: NoiseEstimate | None = None
        self._camera_key: tuple | None = None

    @property
    def estimate(self) -> NoiseEstimate | None:
        """The current estimate, None before the first frame."""
        return self._estimate

    def reset(self) -> None:
        self._parts.clear()
        self._previous = None
        self._estimate = None
        self._camera_key = None

    def update(self, raw: np.ndarray, camera: Camera, static_mask: np.ndarray | None = None, *,
               signal: np.ndarray | None = None) -> NoiseEstimate:
        """Add one frame and return the refined estimate.

        Args:
            raw: uint (H, W) raw frame as delivered.
            camera: its camera; a change of pattern, colour filter, levels or shape starts over.
            static_mask: bool (H, W), pixels known not to have changed since the previous frame (e.g.
                the motion test's static pixels); None uses no temporal samples (a moving camera
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
            self._estimate = NoiseEstimate(sensor.gain, sensor.read_noise, 0.0, 0.0, 0, "given")
            return self._estimate
        sig, floor = _signal_of(raw, camera, signal)
        samples, _ = frame_samples(raw, camera, signal=sig, config=self.config)
        if samples.size:
            self._parts.append(samples)
        if static_mask is not None and self._previous is not None:
            static = np.asarray(static_mask, bool)
            if static.shape != sig.shape:
                raise SveliveError(f"static mask has shape {static.shape} but the frame {sig.shape}")
            part = temporal_samples(self._previous, sig, static, floor, _high_level(sensor),
                                    self.temporal_per_frame)
            if part.size:
                self._parts.append(part)
        self._previous = sig.copy() if signal is not None else sig
        pooled = NoiseSamples.join(list(self._parts))
        config = self.config
        fit = fit_line(*bin_samples(pooled, config), **_fixed(sensor), outlier_tolerance=config.outlier_tolerance)
        self._estimate = estimate_from_fit(fit, sensor, pooled.size)
        return self._estimate
