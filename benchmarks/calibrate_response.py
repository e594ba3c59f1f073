"""Response calibration: one 8-bit SVE frame (svelive) against OpenCV's Debevec on a 4-exposure 8-bit stack;
with ``--sweep``, SVE frames at several global exposure times fitted together (issue 14).

Usage: python benchmarks/calibrate_response.py [--data ../shared/data/hdr] [--scenes Cannon,MtTamWest,Desk,Bonita,Garden,BrightRings]
       [--curves linear,gamma2.2,poly3,s-curve] [--diagnose]
       python benchmarks/calibrate_response.py --sweep "1,1.5;1,1.5,2.25" [--bits 8,12] [--scenes ...] [--curves ...]
           [--max-knots 0] [--seed 1]

``--sweep``: for every scene, curve, bit depth and sweep (global exposure times, ``;`` between
sweeps), the frames at those times (independent noise) are fitted together; the row gives the
chosen model (``deg d``: polynomial of degree d; ``spline k``: log-spline with k knots), the largest error over the measured range, that range, the largest standard error
of the uncertainty band and the fraction of the band's 33 points whose true value lies within
+-2 standard errors. ``--seed``: the noise of the first frame (the others take the next seeds), to
tell a fit's noise from its bias.
Both see the same scene through the same known response (CURVES) and sensor noise;
the error is the largest |f_fit(M) - f_true(M)| over the brightness range each
method measured (Debevec's curve is scaled so f(255) = 1, like ours).

``--diagnose`` (no Debevec) separates the fit's two error sources, per scene and curve:
- ``noise-free``: the same locations and weights, but every equation made exact
  (the brighter exposure's value replaced by the one the true curve predicts from
  the darker one), refitted at the chosen degree: the error that remains is the
  estimator's and the polynomial's, not the noise's;
- ``dchi2 periodic`` / ``dchi2 smooth``: change of the fit's chi-square (residuals
  normalised by the noise propagated through the slope) when the true curve is
  deformed by ``f (1 + 0.05 (sin(2 pi log_4 f + pi/2) - 1))`` (which every equation
  between exposures whose ratio is a power of 4 satisfies exactly) or by the smooth
  ``f (1 + 0.2 M (1 - M))`` (about as large); with the frame's exposures 1, 4, 16, 64
  the first is invisible to the data and the second is not.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time

import cv2
import numpy as np
from numpy.polynomial import polynomial as P

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # this checkout, not an editable install's

from svelive import Pattern, Sensor  # noqa: E402
from svelive.calibrate import CURVES, ResponseFitConfig, fit_response, simulate_nonlinear  # noqa: E402
from svelive.calibrate import response as response_module  # noqa: E402
from svelive.exr import read_luminance  # noqa: E402
from svelive.simulation import exposure_scale  # noqa: E402


def debevec_error(radiance: np.ndarray, levels: np.ndarray, sensor: Sensor, curve, seed: int) -> float:
    frames = [simulate_nonlinear(radiance, str(float(e)), sensor, curve, seed=seed + i) for i, e in enumerate(levels)]
    stack = [cv2.merge([f, f, f]) for f in frames]
    response = cv2.createCalibrateDebevec().process(stack, np.asarray(levels, np.float32))[:, 0, 0].astype(np.float64)
    f = response / response[255]
    codes = np.arange(256)
    used = (codes >= 2) & (codes <= 253)
    return float(np.max(np.abs(f[used] - curve.inverse(codes[used] / 255.0))))


def chi_square(pairs, exposures: np.ndarray, f) -> float:
    """Sum of the squared ratio residuals f(m_hi)/R - f(m_lo), normalised by the window noise through f'."""
    inv_r = exposures[pairs.k_lo] / exposures[pairs.k_hi]

    def slope(m: np.ndarray) -> np.ndarray:
        lo, hi = np.maximum(m - 1e-6, 0.0), np.minimum(m + 1e-6, 1.0)
        return (f(hi) - f(lo)) / (hi - lo)

    r = f(pairs.m_hi) * inv_r - f(pairs.m_lo)
    s2 = (slope(pairs.m_hi) * inv_r) ** 2 * pairs.var_hi + slope(pairs.m_lo) ** 2 * pairs.var_lo
    return float(np.sum(r * r / s2))


def diagnose(raw: np.ndarray, pattern: Pattern, sensor: Sensor, curve) -> str:
    """One table row: the fit's error on the frame and on noise-free equations, and the chi-square
    change of a periodic (ratio-invisible) and of a smooth deformation of the true curve."""
    r = fit_response(raw, pattern, sensor)
    lo, hi = r.stats["measured_range"]
    m = np.linspace(lo, hi, 1000)
    exposures = np.asarray(r.stats["exposures"])
    pairs = response_module._collect_pairs(raw, pattern, sensor, ResponseFitConfig())
    inv_r = exposures[pairs.k_lo] / exposures[pairs.k_hi]
    exact = dataclasses.replace(pairs, m_hi=curve.forward(np.clip(curve.inverse(pairs.m_lo) / inv_r, 0.0, 1.0)))
    coef = response_module._solve(exact, exposures, r.degree)
    f = curve.inverse
    periodic = lambda x: f(x) * (1 + 0.05 * (np.sin(2 * np.pi * np.log(np.maximum(f(x), 1e-12)) / np.log(4) + np.pi / 2) - 1))
    smooth = lambda x: f(x) * (1 + 0.2 * x * (1 - x))
    grid = np.linspace(0.0, 1.0, 1001)
    base = chi_square(pairs, exposures, f)
    return (f"{r.degree} | {np.max(np.abs(r(m) - f(m))):.4f} | {np.max(np.abs(P.polyval(m, coef) - f(m))):.4f} | "
            f"{pairs.m_lo.size} | {base:.0f} | "
            f"{np.max(np.abs(periodic(grid) - f(grid))):.3f}: {chi_square(pairs, exposures, periodic) - base:+.0f} | "
            f"{np.max(np.abs(smooth(grid) - f(grid))):.3f}: {chi_square(pairs, exposures, smooth) - base:+.0f}")


def sweep_rows(radiance: np.ndarray, pattern: Pattern, sensor: Sensor, curve, sweeps: list[list[float]],
               seed: int = 1, config: ResponseFitConfig = ResponseFitConfig()) -> list[str]:
    """One table row per sweep: frames, degree, error, measured range, band, band coverage, seconds."""
    rows = []
    for times in sweeps:
        frames = [simulate_nonlinear(radiance * t, pattern, sensor, curve, seed=seed + i) for i, t in enumerate(times)]
        t0 = time.perf_counter()
        try:
            r = fit_response(frames if len(frames) > 1 else frames[0], pattern, sensor, config,
                             exposure_times=times if len(frames) > 1 else None)
            lo, hi = r.stats["measured_range"]
            m = np.linspace(lo, hi, 1000)
            band = r.stats["band"]
            bm, se = np.asarray(band["brightness"]), np.asarray(band["standard_error"])
            covered = float(np.mean(np.abs(np.asarray(band["linear"]) - curve.inverse(bm)) <= 2 * se))
            model = f"deg {r.degree}" if r.model == "polynomial" else f"spline {len(r.knots)}"
            row = (f"{model} | {np.max(np.abs(r(m) - curve.inverse(m))):.4f} | {lo:.3f}-{hi:.3f} | "
                   f"{se.max():.4f} | {covered:.2f}")
        except Exception as exc:  # report, keep going
            row = f"- | refused: {exc} | - | - | -"
        rows.append(f"{len(times)} ({','.join(f'{t:g}' for t in times)}) | {row} | {time.perf_counter() - t0:.1f}")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default="../shared/data/hdr")
    ap.add_argument("--scenes", default="Cannon,MtTamWest,Desk,Bonita,Garden,BrightRings")
    ap.add_argument("--curves", default=",".join(CURVES))
    ap.add_argument("--diagnose", action="store_true", help="error sources instead of the Debevec comparison")
    ap.add_argument("--sweep", help="global exposure times of the frames fitted together, ';' between sweeps, "
                                    "e.g. '1,1.5;1,1.5,2.25' (no Debevec)")
    ap.add_argument("--bits", default="8", help="bit depths, comma-separated (default 8)")
    ap.add_argument("--max-knots", type=int, default=None,
                    help="with --sweep: the log-spline model offered, with N knots and as a power law (2 knots) "
                         "(default: the library's, svelive.calibrate.response.SWEEP_KNOTS; 0: polynomials only)")
    ap.add_argument("--seed", type=int, default=1, help="with --sweep: noise seed of the first frame (default 1)")
    args = ap.parse_args()
    if args.sweep:
        sweeps = [[float(t) for t in part.split(",")] for part in args.sweep.split(";")]
        pattern = Pattern.parse("1,4/16,64")
        print("scene | curve | bits | frames (times) | model | max error | measured range | band max s.e. | "
              "truth within 2 s.e. | s")
        for scene_name in args.scenes.split(","):
            scene = read_luminance(f"{args.data}/{scene_name}.exr")
            for bits in (int(b) for b in args.bits.split(",")):
                sensor = Sensor.from_full_well(bits, 10000, 3)
                radiance = scene * exposure_scale(scene, pattern, sensor)
                for name in args.curves.split(","):
                    for row in sweep_rows(radiance, pattern, sensor, CURVES[name], sweeps, seed=args.seed,
                                          config=ResponseFitConfig() if args.max_knots is None
                                          else ResponseFitConfig(max_knots=args.max_knots)):
                        print(f"{scene_name} | {name} | {bits} | {row}", flush=True)
        return
    sensor = Sensor.from_full_well(8, 10000, 3)
    pattern = Pattern.parse("1,4/16,64")
    if args.diagnose:
        print("scene | curve | degree | error | error on noise-free equations | equations | chi2 | "
              "periodic deformation: size: dchi2 | smooth deformation: size: dchi2")
    else:
        print("scene | curve | SVE degree | SVE max error | SVE range | SVE s | Debevec max error | Debevec s")
    for scene_name in args.scenes.split(","):
        scene = read_luminance(f"{args.data}/{scene_name}.exr")
        radiance = scene * exposure_scale(scene, pattern, sensor)
        for name in args.curves.split(","):
            curve = CURVES[name]
            raw = simulate_nonlinear(radiance, pattern, sensor, curve, seed=1)
            if args.diagnose:
                try:
                    print(f"{scene_name} | {name} | {diagnose(raw, pattern, sensor, curve)}", flush=True)
                except Exception as exc:  # report, keep going
                    print(f"{scene_name} | {name} | refused: {exc}", flush=True)
                continue
            t = time.perf_counter()
            try:
                r = fit_response(raw, pattern, sensor)
                lo, hi = r.stats["measured_range"]
                m = np.linspace(lo, hi, 1000)
                sve = f"{r.degree} | {np.max(np.abs(r(m) - curve.inverse(m))):.4f} | {lo:.3f}-{hi:.3f}"
            except Exception as exc:  # report, keep going
                sve = f"- | refused: {exc} | -"
            t_sve = time.perf_counter() - t
            t = time.perf_counter()
            deb = debevec_error(radiance, pattern.levels, sensor, curve, seed=10)
            t_deb = time.perf_counter() - t
            print(f"{scene_name} | {name} | {sve} | {t_sve:.2f} | {deb:.4f} | {t_deb:.2f}", flush=True)


if __name__ == "__main__":
    main()
