"""The fit (:func:`fit_response`, steps 1-7 of svelive.calibrate.response) and the service's calibration
of live frames (:func:`calibrate_frame`): the frames checked, the candidate models fitted and chosen,
the optional re-estimation of the exposure ratios, and the fit's statistics."""

from __future__ import annotations

from typing import Callable

import numpy as np

from svelive.calibrate.response.config import SWEEP_KNOTS, ResponseFitConfig
from svelive.calibrate.response.pairs import _collect_pairs, _Pairs, _subset, _too_few, _undithered
from svelive.calibrate.response.polynomial import _curve_uncertainty, _design, _residual_sigma, _solve
from svelive.calibrate.response.selection import (
    _held_out,
    _held_out_curve,
    _jackknife_error,
    _model_name,
    _monotone,
    _monotone_curve,
    _pinned_range,
)
from svelive.calibrate.response.spline import _censored_with_pilot, _solve_spline, _spline_uncertainty, spline_knots
from svelive.core.errors import SveliveError
from svelive.core.pattern import Pattern
from svelive.core.response import Response
from svelive.core.sensor import Sensor


def _refine_exposures(pairs: _Pairs, exposures: np.ndarray, curve: Response) -> np.ndarray:
    """Exposures re-estimated from f(m_hi) / f(m_lo), with the extreme ratio kept nominal."""
    f_lo, f_hi = curve(pairs.m_lo), curve(pairs.m_hi)
    ok = (f_lo > 0.01) & (f_hi > 0.01)
    K = exposures.size
    if not ok.any():
        return exposures
    # log e_hi - log e_lo = log(f_hi / f_lo), least squares with log e_0 fixed
    A = np.zeros((int(ok.sum()), K))
    rows = np.arange(A.shape[0])
    A[rows, pairs.k_hi[ok]] += 1.0
    A[rows, pairs.k_lo[ok]] -= 1.0
    b = np.log(f_hi[ok] / f_lo[ok])
    observed = np.unique(np.concatenate([pairs.k_lo[ok], pairs.k_hi[ok]]))
    if 0 not in observed or K - 1 not in observed:
        return exposures
    log_e, *_ = np.linalg.lstsq(A[:, 1:], b, rcond=None)
    log_e = np.concatenate([[0.0], log_e])
    nominal = np.log(exposures / exposures[0])
    if not log_e[-1] > 0:
        return exposures
    log_e *= nominal[-1] / log_e[-1]
    return exposures[0] * np.exp(log_e)


def common_ratio(exposures: np.ndarray, max_power: int = 12, tolerance: float = 1e-3) -> float | None:
    """The ratio R of which every exposure ratio is an integer power, or None when there is none.

    Ratio equations then hold equally for ``f`` and for ``f(M) p(log_R f(M))`` with
    any p periodic of period 1 (a log-periodic ripple), so one frame cannot tell
    them apart: only the polynomial model does, well for curves a low-degree
    polynomial follows, by several % for S-shaped film curves (docs/calibration.md).
    Two exposure levels always have one. Found as the largest R = r^(1/k),
    r the smallest ratio and k <= ``max_power``, whose powers give every ratio
    within ``tolerance`` (relative, in the logarithm).

    Args:
        exposures: (N,) positive exposure levels, any order.
    """
    logs = np.log(np.unique(np.asarray(exposures, np.float64)))
    steps = logs[1:] - logs[0]
    if steps.size == 0:
        return None
    for k in range(1, max_power + 1):
        unit = steps[0] / k
        powers = steps / unit
        if np.all(np.abs(powers - np.round(powers)) <= tolerance * np.maximum(powers, 1.0)):
            return float(f"{np.exp(unit):.6g}")
    return None


def _check_frames(raw: np.ndarray | list[np.ndarray], exposure_times) -> tuple[list[np.ndarray], np.ndarray]:
    """The frames as a list and their exposure times (float64 (J,), ones for a single frame)."""
    raws = [np.asarray(raw)] if isinstance(raw, np.ndarray) else [np.asarray(r) for r in raw]
    if not raws:
        raise SveliveError("response calibration needs at least one frame")
    for i, r in enumerate(raws):
        which = "raw frame" if len(raws) == 1 else f"frame {i + 1}"
        if r.ndim != 2 or r.size == 0:
            raise SveliveError(f"{which} must be a non-empty single-channel 2-D array, got shape {r.shape}")
        if r.dtype.kind not in "ui":
            raise SveliveError(f"response calibration takes the camera's integer raw values, got {r.dtype}")
        if r.shape != raws[0].shape:
            raise SveliveError(f"frame {i + 1} is {r.shape[1]}x{r.shape[0]}, frame 1 "
                               f"{raws[0].shape[1]}x{raws[0].shape[0]}: give frames of one camera and region")
    if exposure_times is None:
        if len(raws) > 1:
            raise SveliveError(f"{len(raws)} frames need their exposure times (--exposure-times T1,T2,...)")
        return raws, np.ones(1)
    times = np.asarray(exposure_times, np.float64).ravel()
    if times.size != len(raws):
        raise SveliveError(f"{times.size} exposure times for {len(raws)} frames: give one per frame")
    if not np.all(np.isfinite(times) & (times > 0)):
        raise SveliveError(f"exposure times must be positive numbers, got {times.tolist()}")
    return raws, times


def fit_response(raw: np.ndarray | list[np.ndarray], pattern: Pattern | str, sensor: Sensor,
                 config: ResponseFitConfig = ResponseFitConfig(), *, exposure_times=None,
                 progress: Callable[[str], None] | None = None) -> Response:
    """Fit the inverse response polynomial to one raw SVE frame, or to frames at several global exposures.

    With several frames of the same still scene taken at global exposure times
    ``t_j``, every (frame j, level k) is one exposure ``t_j e_k``: the ratio
    equations within each frame and between every two frames enter one fit with
    their noise weights. Exposure ratios that are not powers of the pattern's
    ratio remove the log-periodic ambiguity of one frame (:func:`common_ratio`).

    Args:
        raw: (H, W) uint8/uint16 raw frame, DN including black, of a static scene
            with smooth areas spanning dark to bright; or a list of such frames.
        pattern: the exposure pattern with its nominal exposures.
        sensor: bit depth, black and white level.
        config: fit options.
        exposure_times: (J,) global exposure time of every frame, any unit (needed
            for more than one frame).
        progress: called with a short text at each stage (e.g. for a progress line).

    Returns:
        The Response; ``stats`` holds the measured brightness range, the number of
        locations and equations, the held-out error of every degree tried, the
        exposures used and the uncertainty band over the measured range.
    """
    raws, times = _check_frames(raw, exposure_times)
    if not 1 <= config.max_degree <= 10:
        raise SveliveError(f"max degree must be 1..10, got {config.max_degree}")
    if not 0 <= config.max_knots <= 16:
        raise SveliveError(f"max knots must be 0..16 (0: polynomials only), got {config.max_knots}")
    if config.window < 3 or config.window % 2 == 0:
        raise SveliveError(f"window must be odd and >= 3 tiles, got {config.window}")
    pattern = Pattern.parse(pattern)
    if pattern.levels.size < 2 and len(raws) < 2:
        raise SveliveError("the pattern has one exposure only; response calibration needs two or more")
    nominal = (times[:, None] / times[0] * pattern.levels.astype(np.float64)[None, :]).ravel()
    pairs = _collect_pairs(raws, pattern, sensor, config, nominal, progress)
    n_locations = int(np.unique(pairs.location).size)
    if n_locations < config.min_locations:
        raise SveliveError(_too_few(n_locations, config.min_locations))
    # any increasing response reads a brighter value at the higher exposure; on data that is not an
    # SVE frame of this pattern (wrong pattern, pure texture or noise) that fails at many locations
    lit = pairs.m_hi > 3.0 * np.sqrt(pairs.var_hi)
    flipped = float(np.mean(pairs.m_hi[lit] <= pairs.m_lo[lit])) if lit.any() else 0.0
    if flipped > 0.1:
        raise SveliveError(
            f"at {flipped:.0%} of the constant regions the higher exposure reads darker than the lower one: "
            + ("this is not an SVE frame of this pattern (check --pattern and the tile origin) or the scene moved"
               if len(raws) == 1 else "check --pattern, the order of the exposure times, and that the scene "
               "and camera stood still"))
    used = np.concatenate([pairs.m_lo, pairs.m_hi])
    measured = (float(np.min(used)), float(np.max(used)))
    if measured[1] - measured[0] < config.min_span:
        raise SveliveError(
            f"the constant regions only cover brightness {measured[0]:.2f}..{measured[1]:.2f} of full scale "
            f"(need a span of {config.min_span:.2f}): use a scene with smooth areas over a wider range of brightness")
    ratio = common_ratio(nominal) if len(raws) == 1 else common_ratio(nominal, max_power=4)
    # the log-spline follows film curves but would also follow the log-periodic ripple one frame cannot
    # see: it is offered only to sweeps, whose exposure ratios are not all powers of one number
    candidates = [("polynomial", d) for d in range(1, config.max_degree + 1)]
    scored = None
    censored = None
    if len(raws) > 1 and ratio is None and config.max_knots >= 2:
        # windows are kept only when no reading is clipped, so a dark one survives when its noise
        # happened to lift it off 0: its value reads high (and its log is biased besides). A flexible
        # model would follow that bias, and held-out error would reward it, so equations whose darker
        # value is within ``dark_snr`` single-reading noise sd of 0 are left to no model here.
        reading_sd = np.sqrt(pairs.var_lo * config.window**2)
        clear = _subset(pairs, pairs.m_lo > config.dark_snr * reading_sd)
        if np.unique(clear.location).size >= config.min_locations:
            pairs = clear
            n_locations = int(np.unique(pairs.location).size)
            ends = (float(pairs.m_lo.min()), float(pairs.m_hi.max()))
            measured = ends
            # two sizes, not a choice of the knot count: held-out error, dominated by the numerous dark
            # equations, cannot see the shoulder, and with no knot beyond the data the fit is stable in
            # the count (docs/calibration.md). A power law (2 knots) for linear and gamma cameras.
            candidates += [("log-spline", k) for k in sorted({2, config.max_knots})]
            pairs = _undithered(pairs, sensor.range_dn)
            # which pixels reach white in the brighter frame pins the curve at white against the darker
            # readings (the scale), free of the texture selection of the windows kept near white
            censored = _censored_with_pilot(raws, times, sensor, pairs, nominal,
                                            np.log(spline_knots(*ends, config.max_knots)))
            # the rounding error of a window is the same at every location of that brightness, so
            # held-out locations share it: models are compared where it is small against the value
            far = pairs.m_lo * sensor.range_dn >= 0.5 / config.rounding_tolerance
            if np.unique(pairs.location[far]).size >= config.min_locations:
                scored = far
    exposures = nominal
    iterations = 8 if config.refine_ratios else 1
    for _ in range(iterations):
        scores = {}
        fits = {}
        fold_fits = {}
        for kind, size in candidates:
            if kind == "polynomial":
                if progress is not None:
                    progress(f"degree {size}/{config.max_degree} ({pairs.m_lo.size} equations)")
                coef = _solve(pairs, exposures, size)
                if not _monotone(coef, measured):
                    continue
                mean, se, held = _held_out(pairs, exposures, size, config.folds, scored)
                held = [Response(tuple(c)) for c in held]
            else:
                if progress is not None:
                    progress(f"log-spline, {size} knots ({pairs.m_lo.size} equations)")
                # the last knot at the top of the data: from there to white, where f(1) = 1 is set, the
                # curve is the power law of the last slope. The ratio equations barely see f(1) / f(top)
                # (the weakest direction of the fit by far), so a spline piece beyond the data, with its
                # curvature free, would set the scale of the whole curve from noise
                knots = tuple(spline_knots(*ends, size))
                knots_u = np.log(knots)
                coef = _solve_spline(pairs, exposures, knots_u, censored=censored)[0]
                if not _monotone_curve(Response(tuple(coef), knots=knots), measured):
                    continue
                mean, se, held = _held_out_curve(
                    pairs, exposures,
                    lambda sel, ku=knots_u: _solve_spline(pairs, exposures, ku, sel, censored=censored)[0],
                    lambda c, kn=knots: Response(tuple(c), knots=kn), config.folds, scored)
                held = [Response(tuple(c), knots=knots) for c in held]
                coef = (coef, knots)
            scores[kind, size] = (mean, se)
            fits[kind, size] = coef
            fold_fits[kind, size] = held
        if not scores:
            raise SveliveError("no polynomial degree gives a monotone response on this data; use a frame with "
                               "more smooth areas, or check the pattern and the black and white levels")
        best = min(scores, key=lambda key: scores[key][0])
        # the simplest model within one standard error of the best: fewest free parameters (a polynomial
        # of degree d has d, a log-spline with k knots k - 1), a polynomial before a spline of as many
        chosen = min((key for key in scores if scores[key][0] <= scores[best][0] + scores[best][1]),
                     key=lambda key: (key[1] - (key[0] == "log-spline"), key[0] == "log-spline"))
        if chosen[0] == "polynomial":
            coef, knots = fits[chosen], ()
        else:
            coef, knots = fits[chosen]
        curve = Response(tuple(float(c) for c in coef), knots=knots)
        if not config.refine_ratios:
            break
        new = _refine_exposures(pairs, exposures, curve)
        converged = np.max(np.abs(np.log(new / exposures))) < 1e-4
        exposures = new
        if converged:
            break
    grid = np.linspace(0.0, 1.0, 513)
    if chosen[0] == "polynomial":
        degree = chosen[1]
        A, y = _design(pairs, exposures, degree)
        sigma = _residual_sigma(pairs, exposures, coef)
        chi2 = float(np.mean(((A @ coef[1:] - y) / sigma) ** 2))
        profile = _curve_uncertainty(A / sigma[:, None], max(chi2, 1.0), grid)
        del A, y, sigma
    else:
        _, a, b = _solve_spline(pairs, exposures, np.log(knots), censored=censored)
        chi2 = float(np.mean((a @ coef[1:] - b) ** 2))
        profile = _spline_uncertainty(a, max(chi2, 1.0), np.log(knots), coef, grid)
        del a, b
    pinned = _pinned_range(pairs, profile, grid, config.max_uncertainty, config.coverage_bins,
                           config.coverage_count)
    if pinned[1] - pinned[0] < config.min_span:
        raise SveliveError(
            f"the frame pins the response down only on brightness {pinned[0]:.2f}..{pinned[1]:.2f} "
            f"(need a span of {config.min_span:.2f} with standard error under {config.max_uncertainty:.1%} and "
            "constant regions at every level): use a frame of a still scene with large smooth areas from dark "
            "to bright and little noise")
    inside = (grid >= pinned[0]) & (grid <= pinned[1])
    uncertainty = float(profile[inside].max())
    band_m = np.linspace(pinned[0], pinned[1], 33)
    band_se = np.maximum(np.interp(band_m, grid, profile), _jackknife_error(fold_fits[chosen], band_m))
    stats = {
        "measured_range": list(pinned),
        "data_range": list(measured),
        "uncertainty": {"brightness": grid[::16].tolist(), "standard_error": profile[::16].tolist()},
        "band": {"brightness": band_m.tolist(), "linear": curve(band_m).tolist(),
                 "standard_error": band_se.tolist()},
        "locations": n_locations,
        "equations": int(pairs.m_lo.size),
        "held_out_error": {_model_name(*key): {"mean": m, "standard_error": s} for key, (m, s) in scores.items()},
        "reduced_chi2": chi2,
        "curve_uncertainty": uncertainty,
        "exposures": exposures.tolist(),
        "nominal_exposures": nominal.tolist(),
        "pattern": str(pattern),
        "frames": len(raws),
        "exposure_times": times.tolist() if exposure_times is not None else None,
        # a sweep's near-coincidences (1.5 against 4 agree to 1e-3 at the 12th root) give ripples no
        # polynomial can follow: only common ratios within the fourth root of the smallest step count
        "common_ratio": ratio,
        # the sweep's pixels near white that pin the log-spline's scale (None: not used)
        "pixels_near_white": None if censored is None else {
            "pixels": int(censored.total.sum()), "at_white": int(censored.clipped.sum()),
            "width": [float(censored.width[censored.pair == q][0]) for q in np.unique(censored.pair)]},
    }
    return Response(curve.coefficients, (0.0, 1.0), float(sensor.black_level), float(sensor.white_level), stats,
                    knots)


def calibrate_frame(raw: np.ndarray | list[np.ndarray], pattern: Pattern | str, sensor: Sensor, *,
                    max_degree: int = 6, max_knots: int = SWEEP_KNOTS, points: int = 65, exposure_times=None,
                    progress: Callable[[str], None] | None = None) -> dict:
    """Response calibration of live raw frames, for the service: the response file's content
    plus ``curve``, ``points`` samples {"brightness": [...], "linear": [...]} of I = f(M) over
    [0, 1] for plotting (``stats.band`` has the uncertainty band over the measured range).
    ``raw`` is one frame, or a list of frames at ``exposure_times`` (a sweep). Raises
    SveliveError when the frames cannot calibrate (too few constant regions, too narrow a
    brightness range). ``max_knots``: see :class:`ResponseFitConfig`."""
    response = fit_response(raw, pattern, sensor, ResponseFitConfig(max_degree=max_degree, max_knots=max_knots),
                            exposure_times=exposure_times, progress=progress)
    m = np.linspace(0.0, 1.0, points)
    data = response.to_dict()
    data["curve"] = {"brightness": m.tolist(), "linear": np.clip(response(m), 0.0, 1.0).tolist()}
    return data
