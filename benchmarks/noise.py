"""The noise model from the data: estimated gain and read noise against the truth, over real HDR scenes.

    python benchmarks/noise.py [--quick] [--data ../shared/data/hdr] [--colour] [--csv out/noise.csv]

Every image x pattern x light x true noise model is simulated like ``svelive bench``
(12-bit, black 64, the lowest exposure just filling at the scene's 99.9th percentile;
then 3, 5 and 7 stops darker), and :func:`svelive.noise.estimate_from_frame` is given the raw frame
and a camera with the pattern, black and white level but no gain and no read noise.
Printed per run: the truth, the estimate, the error in % and the estimate's own
standard uncertainty (sigma, in %), the worst error of the noise standard deviation the
estimate predicts over signals 1..white DN ("sd err": what the noise-aware weights feel,
however gain and read noise split it), and the time. A summary gives the worst errors
and the share of runs within 15 %. ``--quick`` runs three noise models on three images. ``--psnr`` also reconstructs
every frame with the default method under the fixed defaults, the estimate and the
true noise model, and reports PU21-PSNR (slow).
With ``--colour`` the scenes are simulated in RGB through the colour layouts of
svelive.core.camera.COLOUR_LAYOUTS instead of the monochrome patterns. With ``--pair`` a second
and a third frame of the same static scene (other noise seeds) are given to a
:class:`svelive.noise.NoiseTracker` after the first (all pixels static), which is what the live
service does; its errors after two and three frames are reported too ("pair", "three"); ``--no-cancellation`` runs the single-frame estimate without texture
cancellation across exposures (the estimator before issue 12.1's third pass), ``--quarter-cells`` with
the cancellation's selection before its fifth pass (the flattest quarter of every bin only);
``--config name=value,...`` sets any :class:`svelive.noise.EstimatorConfig` field (an A/B of one knob, e.g.
``cancel_symmetric=false,cancel_when_biased=false``: the joint fit and choice before the sixth pass). A run is
"confidently wrong" when a value misses by more than 15 % and by more than two of its own stated
standard uncertainties (in log space). ``--table CSV`` prints the
summary of an earlier run again. ``--runs N`` feeds a fresh :class:`svelive.noise.NoiseTracker` N runs of
three frames of the same static scene (independent noise per frame), exactly as the live service's noise
stage does every 5 s (the first frame of a run without a static mask, the next two with every pixel
static), and reports the tracker's estimate after 1, 2, 4, ... N runs (:func:`convergence_table`).

"bound" is what no estimator can beat: the Cramer-Rao bounds on gain and read noise from
that frame for an estimator that knew every pixel's expected signal (:func:`oracle_sigma_pct`).
The summary splits the runs by it: where both bounds are under 7.5 % the frame tells the
noise model to 15 % at two standard deviations; where one is over, no method can promise 15 %
(e.g. a read noise of 0.7 DN in a bright frame, where shot noise swamps it everywhere).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # this checkout, not an editable install's

from svelive.bench.scenes import default_data_dir, find_images, load_scene, shipped_data_dir  # noqa: E402
from svelive.core.camera import COLOUR_LAYOUTS, Camera  # noqa: E402
from svelive.core.pattern import Pattern  # noqa: E402
from svelive.core.sensor import Sensor  # noqa: E402
from svelive.exr import read_exr  # noqa: E402
from svelive.noise import EstimatorConfig, NoiseTracker, estimate_from_frame  # noqa: E402
from svelive.simulation import exposure_scale, simulate  # noqa: E402

PATTERNS = ("1,4/16,64", "1,2/4,8", "1/1/8/8")
#: light levels: stops below the fill of the lowest exposure (issue 12: bright, -3, -5, -7)
LIGHTS = {"bright": 0.0, "-3": 3.0, "-5": 5.0, "-7": 7.0}
#: (full well e-, read noise DN): the bench sensor's (10 000 e-, 2 DN) and the corners of a wide range.
NOISE_MODELS = ((10_000, 2.0), (3_000, 6.0), (40_000, 0.7), (3_000, 0.7), (40_000, 6.0), (20_000, 1.2))
QUICK_MODELS = ((10_000, 2.0), (3_000, 6.0), (40_000, 0.7))
BITS, BLACK = 12, 64
#: a one-frame Cramer-Rao bound (oracle_sigma_pct) above this, in %, puts 15 % within two standard deviations
BOUND_TOLD_PCT = 7.5


def sd_error(gain: float, read: float, true_gain: float, true_read: float, white: float = 2**BITS - 1 - BLACK) -> float:
    """Worst relative error (%) of the noise standard deviation the estimate predicts, over signals
    1..white DN (log-spaced): what the noise-aware weights feel, however gain and read noise split it."""
    s = np.geomspace(1.0, white, 64)
    est = np.sqrt(s / gain + read**2 + 1 / 12)
    true = np.sqrt(s / true_gain + true_read**2 + 1 / 12)
    return float(100 * np.max(np.abs(est / true - 1)))


def oracle_sigma_pct(truth: np.ndarray, pattern: Pattern, sensor: Sensor, cfa: str | None = None
                     ) -> tuple[float, float]:
    """The Cramer-Rao bounds on gain and read noise from one frame, relative standard deviations in %.

    What an estimator could reach that knew every pixel's expected signal (the
    scene's texture exactly) and had only to read gain and read noise from the
    readings' spread: readings are Gaussian with variance v = mu / gain + r^2 +
    1/12 (DN^2), so the Fisher information of (1/gain, r^2) is the sum over
    unclipped pixels of [mu, 1]^T [mu, 1] / (2 v^2). A run whose bound is above
    7.5 % cannot be within 15 % reliably by any estimator (15 % is then under two
    of its standard deviations); n frames divide the bound by sqrt(n). The same for
    the read noise r (half the relative bound of r^2).

    ``truth``: float32 (H, W), or (H, W, 3) with ``cfa``, radiance in DN at
    relative exposure 1 (``SimulatedFrame.truth``).
    """
    if truth.ndim == 3:
        from svelive.core.cfa import ColourFilter
        index = ColourFilter.parse(cfa).channel_map(truth.shape[:2])
        truth = np.take_along_axis(truth, index[..., None], axis=-1)[..., 0]
    mu = (truth * pattern.exposure_map(truth.shape)).astype(np.float64).ravel()
    mu = mu[mu + 3 * np.sqrt(sensor.signal_variance(mu)) < sensor.censor_level]
    v = sensor.signal_variance(mu)
    w = 0.5 / (v * v)
    fisher = np.array([[np.sum(w * mu * mu), np.sum(w * mu)], [np.sum(w * mu), np.sum(w)]])
    cov = np.linalg.inv(fisher)
    return (float(100 * np.sqrt(cov[0, 0]) * sensor.gain),
            float(100 * 0.5 * np.sqrt(cov[1, 1]) / sensor.read_noise**2))


def confidently_wrong(error_pct: float, sigma_pct: float) -> bool:
    """A miss of more than 15 % that the stated uncertainty does not cover: the truth more than 2 sigma
    away in log space (``sigma_pct`` is sigma over the estimate, a log-sigma: the prior is log-normal);
    no sigma stated counts as not covered."""
    log_miss = abs(np.log1p(error_pct / 100.0))
    return abs(error_pct) > 15 and not log_miss <= 2 * (sigma_pct / 100.0 if np.isfinite(sigma_pct) else 0.0)


def checkpoints(runs: int) -> list[int]:
    """1, 2, 4, ... up to ``runs``, and ``runs`` itself."""
    out = [1 << i for i in range(runs.bit_length()) if 1 << i <= runs]
    return out + ([runs] if out[-1] != runs else [])


def tracked_errors(name: str, est, truth: Sensor) -> dict:
    """An estimate's errors and stated uncertainties (%) as the row fields ``{name}_gain_error_pct`` etc."""
    return {f"{name}_gain_error_pct": 100 * (est.gain / truth.gain - 1),
            f"{name}_read_noise_error_pct": 100 * (est.read_noise / truth.read_noise - 1),
            f"{name}_gain_sigma_pct": 100 * (est.gain_sigma or float("nan")) / est.gain,
            f"{name}_read_noise_sigma_pct": 100 * (est.read_noise_sigma or float("nan")) / max(est.read_noise, 1e-9)}


def tracker_runs(radiance: np.ndarray, pattern: Pattern, truth: Sensor, cfa: str | None, seed: int, camera: Camera,
                 runs: int) -> list:
    """The estimates of a fresh NoiseTracker after each of ``runs`` runs of three frames of ``radiance``.

    As a stream's model (svelive.noise.StreamNoise, the library's and the live service's) feeds it: every run, the first frame
    without a static mask, the next two with one (here every pixel: the scene is static). Frame ``j``
    (0, 1, 2, ... over all runs) has the noise seed ``seed + 1000 j``: the first run's three frames are
    those of ``--pair``.
    """
    tracker, static, out = NoiseTracker(), None, []
    for r in range(runs):
        for j in range(3):
            raw = simulate(radiance, pattern, truth, cfa=cfa, seed=seed + 1000 * (3 * r + j)).raw
            if static is None:
                static = np.ones(raw.shape, bool)
            estimate = tracker.update(raw, camera, static if j else None)
        out.append(estimate)
    return out


def convergence_table(rows: list[dict], runs: int) -> str:
    """Markdown table: after 1, 2, 4, ... ``runs`` runs of the tracker, the share of runs with gain, read noise
    and both within 15 %, and with either confidently wrong; over all runs and by what one frame can tell."""
    groups: list[tuple[str, list[dict]]] = [("all", rows)]
    if "bound_gain_pct" in rows[0]:
        told = [max(r["bound_gain_pct"], r["bound_read_noise_pct"]) <= BOUND_TOLD_PCT for r in rows]
        groups.append(("frame tells both", [r for r, t in zip(rows, told) if t]))
        groups.append(("frame does not tell both", [r for r, t in zip(rows, told) if not t]))
    head = ("| grid runs | n | tracker runs (x 5 s) | gain within 15 % | read noise within 15 % | both within 15 % | "
            "gain confidently wrong | read noise confidently wrong |")
    lines = [head, "|" + " --- |" * (head.count("|") - 1)]
    for label, mine in groups:
        if not mine:
            continue
        for k in checkpoints(runs):
            g = np.array([abs(r[f"runs{k}_gain_error_pct"]) <= 15 for r in mine])
            e = np.array([abs(r[f"runs{k}_read_noise_error_pct"]) <= 15 for r in mine])
            wg = np.mean([confidently_wrong(r[f"runs{k}_gain_error_pct"], r[f"runs{k}_gain_sigma_pct"]) for r in mine])
            wr = np.mean([confidently_wrong(r[f"runs{k}_read_noise_error_pct"], r[f"runs{k}_read_noise_sigma_pct"])
                          for r in mine])
            lines.append(f"| {label} | {len(mine)} | {k} | {g.mean():.0%} | {e.mean():.0%} | {(g & e).mean():.0%} | "
                         f"{wg:.0%} | {wr:.0%} |")
    return "\n".join(lines)


def summary_table(rows: list[dict]) -> str:
    """Markdown table: per light, pattern, noise model and image, the share within 15 % and the share
    confidently wrong (single frame; and the two-frame tracker when it ran)."""
    groups: list[tuple[str, list[dict]]] = [("all", rows)]
    for key in ("light", "pattern", "image"):
        for value in dict.fromkeys(r[key] for r in rows):
            groups.append((f"{key} {value}", [r for r in rows if r[key] == value]))
    if "bound_gain_pct" in rows[0]:
        told = [max(r["bound_gain_pct"], r["bound_read_noise_pct"]) <= BOUND_TOLD_PCT for r in rows]
        groups.append((f"frame tells both (bounds <= {BOUND_TOLD_PCT} %)", [r for r, t in zip(rows, told) if t]))
        groups.append(("frame does not tell both", [r for r, t in zip(rows, told) if not t]))
    for model in dict.fromkeys((r["full_well"], r["true_read_noise"]) for r in rows):
        groups.append((f"{model[0]:.0f} e-, {model[1]:.1f} DN",
                       [r for r in rows if (r["full_well"], r["true_read_noise"]) == model]))
    tracked = [n for n in ("pair", "three") if f"{n}_gain_error_pct" in rows[0]]
    head = ("| runs | n | gain within 15 % | gain confidently wrong | read noise within 15 % | "
            "read noise confidently wrong | gain median abs error |"
            + "".join(f" {n}: gain within 15 % | {n}: gain confidently wrong | {n}: read noise within 15 % |"
                      for n in tracked))
    lines = [head, "|" + " --- |" * (head.count("|") - 1)]
    for label, mine in groups:
        if not mine:
            continue
        eg = np.array([r["gain_error_pct"] for r in mine])
        er = np.array([r["read_noise_error_pct"] for r in mine])
        wg = np.mean([confidently_wrong(r["gain_error_pct"], r["gain_sigma_pct"]) for r in mine])
        wr = np.mean([confidently_wrong(r["read_noise_error_pct"], r["read_noise_sigma_pct"]) for r in mine])
        line = (f"| {label} | {len(mine)} | {np.mean(abs(eg) <= 15):.0%} | {wg:.0%} | {np.mean(abs(er) <= 15):.0%} | "
                f"{wr:.0%} | {np.median(abs(eg)):.0f} % |")
        for n in tracked:
            pg = np.array([r[f"{n}_gain_error_pct"] for r in mine])
            pr = np.array([r[f"{n}_read_noise_error_pct"] for r in mine])
            pw = np.mean([confidently_wrong(r[f"{n}_gain_error_pct"], r[f"{n}_gain_sigma_pct"]) for r in mine])
            line += f" {np.mean(abs(pg) <= 15):.0%} | {pw:.0%} | {np.mean(abs(pr) <= 15):.0%} |"
        lines.append(line)
    return "\n".join(lines)


def true_sensor(full_well: float, read_noise: float) -> Sensor:
    white = float(2**BITS - 1)
    return Sensor(BITS, BLACK, white, full_well / (white - BLACK), read_noise)


def load_rgb(path: Path) -> np.ndarray:
    channels, _ = read_exr(path)
    rgb = np.stack([channels[c] for c in "RGB"], axis=-1)
    h, w = rgb.shape[:2]
    rgb = rgb[: h - h % 4, : w - w % 4]
    return np.clip(np.nan_to_num(rgb, nan=0.0, posinf=0.0, neginf=0.0), 0, None).astype(np.float32)


def pu21_by_noise_model(raw: np.ndarray, camera: Camera, truth: Sensor, estimate, reference: np.ndarray) -> dict:
    """PU21-PSNR (dB) of the default method with the fixed defaults, the estimate and the true noise model."""
    import svelive
    from svelive.metrics import luminance, pu21_psnr

    def score(image: np.ndarray) -> float:
        return pu21_psnr(luminance(image) if image.ndim == 3 else image,
                         luminance(reference) if reference.ndim == 3 else reference)

    return {"pu21_default": score(svelive.reconstruct(raw, camera, noise="default")),
            "pu21_estimated": score(svelive.reconstruct(raw, camera, noise=estimate)),
            "pu21_true": score(svelive.reconstruct(raw, camera.replace(sensor=truth)))}


def run(images: list[Path], patterns: list[tuple[str, str | None]], models, seed: int, out_csv: Path | None,
        psnr: bool = False, pair: bool = False, lights: dict[str, float] = LIGHTS,
        config: EstimatorConfig = EstimatorConfig(), runs: int = 0) -> int:
    rows = []
    header = (f"{'image':10s} {'pattern':26s} {'light':6s} {'true g':>7s} {'est g':>7s} {'err':>6s} {'sig':>5s}  "
              f"{'true r':>6s} {'est r':>6s} {'err':>6s} {'sig':>5s} {'sd err':>6s} {'samples':>8s} {'ms':>6s}")
    print(header, flush=True)
    total = len(images) * len(patterns) * len(lights) * len(models)
    done = 0
    for path in images:
        colour = any(cfa for _, cfa in patterns)
        scene = load_rgb(path) if colour else load_scene(path)
        for pattern, cfa in patterns:
            for light, stops in lights.items():
                for full_well, read in models:
                    truth = true_sensor(full_well, read)
                    p = Pattern.parse(pattern)
                    radiance = scene * np.float32(exposure_scale(scene, p, truth, stops_below_fill=stops))
                    sim = simulate(radiance, p, truth, cfa=cfa, seed=seed)
                    raw = sim.raw
                    camera = Camera.build(pattern, cfa, Sensor(BITS, BLACK))
                    t0 = time.perf_counter()
                    est = estimate_from_frame(raw, camera, config=config)
                    ms = (time.perf_counter() - t0) * 1e3
                    eg = 100 * (est.gain / truth.gain - 1)
                    er = 100 * (est.read_noise / truth.read_noise - 1)
                    sg = 100 * (est.gain_sigma or float("nan")) / est.gain
                    sr = 100 * (est.read_noise_sigma or float("nan")) / max(est.read_noise, 1e-9)
                    sde = sd_error(est.gain, est.read_noise, truth.gain, truth.read_noise)
                    bound_g, bound_r = oracle_sigma_pct(sim.truth, p, truth, cfa)
                    name = pattern if cfa is None else f"{pattern} {cfa}"
                    done += 1
                    flag = ("" if abs(eg) <= 15 and abs(er) <= 15 else "  <-") + f"  bound {bound_g:.1f}%/{bound_r:.1f}%"
                    scores = pu21_by_noise_model(raw, camera, truth, est, sim.truth) if psnr else {}
                    if pair:
                        tracker = NoiseTracker()
                        tracker.update(raw, camera)
                        second = simulate(radiance, p, truth, cfa=cfa, seed=seed + 1000).raw
                        two = tracker.update(second, camera, np.ones(raw.shape, bool))
                        third = simulate(radiance, p, truth, cfa=cfa, seed=seed + 2000).raw
                        three = tracker.update(third, camera, np.ones(raw.shape, bool))
                        for name_, est_ in (("pair", two), ("three", three)):
                            scores.update(tracked_errors(name_, est_, truth))
                            flag += (f"  {name_} {scores[f'{name_}_gain_error_pct']:+.0f}%/"
                                     f"{scores[f'{name_}_read_noise_error_pct']:+.0f}%")
                    if runs:
                        after = tracker_runs(radiance, p, truth, cfa, seed, camera, runs)
                        for k in checkpoints(runs):
                            scores.update(tracked_errors(f"runs{k}", after[k - 1], truth))
                        flag += "  runs " + " ".join(f"{k}:{scores[f'runs{k}_gain_error_pct']:+.0f}%/"
                                                     f"{scores[f'runs{k}_read_noise_error_pct']:+.0f}%"
                                                     for k in checkpoints(runs))
                    if psnr:
                        flag += "  PU21 default/estimated/true " + "/".join(f"{scores[k]:.2f}" for k in
                                                                   ("pu21_default", "pu21_estimated", "pu21_true"))
                    print(f"{path.stem[:10]:10s} {name[:26]:26s} {light:6s} {truth.gain:7.3f} {est.gain:7.3f} "
                          f"{eg:+5.0f}% {sg:4.0f}%  {truth.read_noise:6.2f} {est.read_noise:6.2f} {er:+5.0f}% "
                          f"{sr:4.0f}% {sde:5.0f}% {est.samples:8d} {ms:6.0f}{flag}   [{done}/{total}]", flush=True)
                    rows.append(dict(image=path.stem, pattern=name, light=light, full_well=full_well,
                                     true_gain=truth.gain,
                                     gain=est.gain, gain_error_pct=eg, gain_sigma_pct=sg,
                                     true_read_noise=truth.read_noise, read_noise=est.read_noise,
                                     read_noise_error_pct=er, read_noise_sigma_pct=sr, sd_error_pct=sde,
                                     bound_gain_pct=bound_g, bound_read_noise_pct=bound_r,
                                     samples=est.samples,
                                     source=est.source, ms=ms, **scores))
    eg = np.array([abs(r["gain_error_pct"]) for r in rows])
    er = np.array([abs(r["read_noise_error_pct"]) for r in rows])
    within = np.mean((eg <= 15) & (er <= 15))
    sde = np.array([r["sd_error_pct"] for r in rows])
    print(f"\n{len(rows)} runs: gain |error| median {np.median(eg):.1f}% worst {eg.max():.1f}%; read noise |error| "
          f"median {np.median(er):.1f}% worst {er.max():.1f}%; both within 15%: {within:.0%}; noise sd (worst over "
          f"1..white DN) error median {np.median(sde):.1f}%, within 15% in {np.mean(sde <= 15):.0%}; "
          f"median time {np.median([r['ms'] for r in rows]):.0f} ms")
    print(summary_table(rows))
    if runs:
        print(convergence_table(rows, runs))
    for key, label in (("gain_error_pct", "gain"), ("read_noise_error_pct", "read noise")):
        worst = sorted(rows, key=lambda r: -abs(r[key]))[:5]
        print(f"worst {label}: " + "; ".join(f"{r['image']} {r['pattern']} {r['light']} g{r['true_gain']:.2f} "
                                             f"r{r['true_read_noise']:.1f}: {r[key]:+.0f}%" for r in worst))
    if psnr:
        pu = np.array([[r["pu21_default"], r["pu21_estimated"], r["pu21_true"]] for r in rows])
        print(f"PU21-PSNR of the default method, mean: fixed defaults {pu[:, 0].mean():.2f}, estimated "
              f"{pu[:, 1].mean():.2f}, true {pu[:, 2].mean():.2f} dB; estimated - defaults from "
              f"{(pu[:, 1] - pu[:, 0]).min():+.2f} to {(pu[:, 1] - pu[:, 0]).max():+.2f} dB")
    if out_csv:
        out_csv.parent.mkdir(parents=True, exist_ok=True)
        with open(out_csv, "w", newline="") as f:
            writer = csv.DictWriter(f, fieldnames=list(rows[0]))
            writer.writeheader()
            writer.writerows(rows)
        print(f"wrote {out_csv}")
    return 0


def time_estimate(patterns: list[str], seed: int, repeats: int = 5) -> int:
    """Print the median wall time of estimate_from_frame on one 1920x1200 frame per pattern and configuration."""
    import cv2

    from svelive.simulation import load_sample_scene

    sensor = Sensor.from_full_well(12, 10_000, 2, black_level=64)
    scene = np.maximum(cv2.resize(load_sample_scene("desk"), (1920, 1200), interpolation=cv2.INTER_CUBIC), 0)
    configs = (("residual fit alone", EstimatorConfig(cancellation=False)),
               ("texture cancelled", EstimatorConfig(cancel_jackknife=0)),
               ("with its jackknife (default)", EstimatorConfig()))
    print(f"# estimate_from_frame, desk crop at 1920x1200, 10000 e- / 2 DN, load {os.getloadavg()[0]:.2f}")
    for pattern in patterns:
        raw = simulate(scene * exposure_scale(scene, Pattern.parse(pattern), sensor), pattern, sensor, seed=seed).raw
        camera = Camera(Pattern.parse(pattern), None, Sensor(bits=12, black_level=64))
        for name, config in configs:
            estimate_from_frame(raw, camera, config=config)  # warm-up (kernels)
            times = []
            for _ in range(repeats):
                start = time.perf_counter()
                estimate = estimate_from_frame(raw, camera, config=config)
                times.append(time.perf_counter() - start)
            print(f"{pattern:10s} {name:30s} {np.median(times) * 1e3:6.0f} ms  gain {estimate.gain:.2f} "
                  f"(true {sensor.gain:.2f})", flush=True)
    return 0


def config_fields(text: str | None) -> dict:
    """``EstimatorConfig`` keyword arguments from 'name=value,...' (bools as true/false)."""
    types = {f.name: f.type for f in dataclasses.fields(EstimatorConfig)}
    out = {}
    for item in filter(None, (text or "").split(",")):
        name, value = (part.strip() for part in item.split("=", 1))
        if name not in types:
            raise SystemExit(f"--config: no EstimatorConfig field {name!r}")
        kind = types[name] if isinstance(types[name], str) else types[name].__name__
        out[name] = (value.lower() in ("1", "true", "yes") if kind == "bool" else
                     int(value) if kind == "int" else float(value))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, help="directory of HDR EXR images (default ../shared/data/hdr, "
                                                  "else the shipped crops)")
    parser.add_argument("--quick", action="store_true", help="three images, three noise models")
    parser.add_argument("--colour", action="store_true", help="colour layouts instead of monochrome patterns")
    parser.add_argument("--images", help="comma-separated image stems")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--csv", type=Path, help="also write the rows as CSV")
    parser.add_argument("--table", type=Path, help="only print the summary table of a CSV this script wrote")
    parser.add_argument("--pair", action="store_true", help="also the tracker's estimates after a second and a "
                                                            "third frame (NoiseTracker, static)")
    parser.add_argument("--runs", type=int, default=0,
                        help="also feed a NoiseTracker N runs of three static frames as the live service does "
                             "(first frame without, the next two with a static mask) and report it after 1, 2, "
                             "4, ... N runs")
    parser.add_argument("--patterns", help="patterns separated by ';' (default: " + "; ".join(PATTERNS) + ")")
    parser.add_argument("--lights", help="comma-separated light names of " + ",".join(LIGHTS))
    parser.add_argument("--models", help="noise models 'full_well:read_dn' separated by ','")
    parser.add_argument("--no-cancellation", action="store_true",
                        help="the single-frame estimate without texture cancellation across exposures (the "
                             "residual fit alone, as before issue 12.1's third pass)")
    parser.add_argument("--quarter-cells", action="store_true",
                        help="the texture cancellation's selection as before issue 12.1's fifth pass: the flattest "
                             "quarter of every bin only, not also every cell whose block is as flat as noise")
    parser.add_argument("--config", help="EstimatorConfig fields as 'name=value' separated by ',', e.g. "
                                          "'cancel_symmetric=false,cancel_when_biased=false' (the single-frame "
                                          "estimate before issue 12.1's sixth pass)")
    parser.add_argument("--psnr", action="store_true", help="also reconstruct with the default method under the "
                                                            "fixed defaults, the estimate and the truth (PU21-PSNR)")
    parser.add_argument("--time", action="store_true",
                        help="only time the single-frame estimate on the shipped desk crop upscaled to 1920x1200 "
                             "(median of 5, each pattern): the residual fit alone, with texture cancellation, and "
                             "with its jackknife uncertainty (the default)")
    args = parser.parse_args(argv)
    if args.time:
        return time_estimate(args.patterns.split(";") if args.patterns else PATTERNS, args.seed)
    if args.table:
        with open(args.table, newline="") as f:
            rows = [{k: (v if k in ("image", "pattern", "light", "source") else float(v or "nan"))
                     for k, v in r.items()} for r in csv.DictReader(f)]
        print(summary_table(rows))
        runs = max((int(k[4:].split("_")[0]) for k in rows[0] if k.startswith("runs") and k.endswith("_gain_error_pct")),
                   default=0)
        if runs:
            print(convergence_table(rows, runs))
        return 0
    data = args.data or (default_data_dir() if default_data_dir().is_dir() else shipped_data_dir())
    images = find_images(data)
    if args.images:
        wanted = set(args.images.split(","))
        images = [p for p in images if p.stem in wanted]
    elif args.quick:
        images = [p for p in images if p.stem.lower() in ("cannon", "desk", "mttamwest")] or images[:3]
    if args.colour:
        patterns = [COLOUR_LAYOUTS[name] for name in COLOUR_LAYOUTS]
    else:
        patterns = [(p, None) for p in (args.patterns.split(";") if args.patterns else PATTERNS)]
    models = QUICK_MODELS if args.quick else NOISE_MODELS
    if args.models:
        models = tuple(tuple(float(v) for v in m.split(":")) for m in args.models.split(","))
    lights = {k: LIGHTS[k] for k in args.lights.split(",")} if args.lights else LIGHTS
    print(f"data {data}: {len(images)} images, {len(patterns)} patterns, {len(lights)} lights, "
          f"{len(models)} noise models", file=sys.stderr)
    config = EstimatorConfig(cancellation=not args.no_cancellation, cancel_flat=not args.quarter_cells,
                             **config_fields(args.config))
    return run(images, patterns, models, args.seed, args.csv, args.psnr, args.pair, lights, config, args.runs)


if __name__ == "__main__":
    sys.exit(main())
