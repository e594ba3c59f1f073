"""Response calibration: one 8-bit SVE frame (svelive) against OpenCV's Debevec on a 4-exposure 8-bit stack.

Usage: python benchmarks/calibrate_response.py [--data ../shared/data/hdr] [--scenes Cannon,MtTamWest,Desk,Bonita,Garden,BrightRings]
Both see the same scene through the same known response (CURVES) and sensor noise;
the error is the largest |f_fit(M) - f_true(M)| over the brightness range each
method measured (Debevec's curve is scaled so f(255) = 1, like ours).
"""

from __future__ import annotations

import argparse
import time

import cv2
import numpy as np

from svelive import Pattern, Sensor
from svelive.calibrate import CURVES, fit_response, simulate_nonlinear
from svelive.exr import read_luminance
from svelive.simulate import exposure_scale


def debevec_error(radiance: np.ndarray, levels: np.ndarray, sensor: Sensor, curve, seed: int) -> float:
    frames = [simulate_nonlinear(radiance, str(float(e)), sensor, curve, seed=seed + i) for i, e in enumerate(levels)]
    stack = [cv2.merge([f, f, f]) for f in frames]
    response = cv2.createCalibrateDebevec().process(stack, np.asarray(levels, np.float32))[:, 0, 0].astype(np.float64)
    f = response / response[255]
    codes = np.arange(256)
    used = (codes >= 2) & (codes <= 253)
    return float(np.max(np.abs(f[used] - curve.inverse(codes[used] / 255.0))))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default="../shared/data/hdr")
    ap.add_argument("--scenes", default="Cannon,MtTamWest,Desk,Bonita,Garden,BrightRings")
    args = ap.parse_args()
    sensor = Sensor.from_full_well(8, 10000, 3)
    pattern = Pattern.parse("1,4/16,64")
    print("scene | curve | SVE degree | SVE max error | SVE range | SVE s | Debevec max error | Debevec s")
    for scene_name in args.scenes.split(","):
        scene = read_luminance(f"{args.data}/{scene_name}.exr")
        radiance = scene * exposure_scale(scene, pattern, sensor)
        for name, curve in CURVES.items():
            raw = simulate_nonlinear(radiance, pattern, sensor, curve, seed=1)
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
            print(f"{scene_name} | {name} | {sve} | {t_sve:.2f} | {deb:.4f} | {t_deb:.2f}")


if __name__ == "__main__":
    main()
