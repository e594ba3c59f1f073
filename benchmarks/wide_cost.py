"""CPU cost of the default method's wide fallback (``adaptive``'s step 5, fallback.wide_fallback) on the bench's dim
timing frames, one thread, and of the whole method.

    python benchmarks/wide_cost.py [--data ../shared/data/hdr] [--frames 3] [--repeats 9] [--compare REV]

The 5 stops dim timing frames (svelive.bench: every HDR image under every pattern, 1920x1200), ranked by the
share of pixels the fallback takes (``adaptive.path_shares``); timed: the ``--frames`` with the largest shares
and the median one. For each, steps 1-4 run once per strip as
``adaptive`` runs them; then the fallback alone on fresh copies of what it changes, this thread's CPU time,
median of ``--repeats`` after a warm-up, and ``adaptive.run`` whole. ``--compare REV`` loads the fallback of
another revision of this repository (its adaptive/fallback.py and the posterior.py it imports, ``git show``
into copies under names of their own, so their kernels compile afresh), times it alternated with this one in
the same process (the fallback, and the whole method with it in place of this one's) and says whether both
give the same bits: on a shared machine only such ratios are worth comparing.
"""

from __future__ import annotations

import argparse
import importlib
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import ModuleType
from typing import Callable

os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

_CHECKOUT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, _CHECKOUT)  # this checkout, not an editable install's

from svelive.bench.runner import timing_frame  # noqa: E402
from svelive.bench.scenes import BENCH_SENSOR, PATTERNS, Condition, find_images, load_scene  # noqa: E402
from svelive.memory import keep_freed_memory  # noqa: E402
from svelive.reconstruction.input import prepare  # noqa: E402
from svelive.reconstruction.methods import adaptive  # noqa: E402
from svelive.reconstruction.methods.adaptive import fallback  # noqa: E402
from svelive.reconstruction.methods.adaptive.parameters import kernels  # noqa: E402
from svelive.reconstruction.methods.base import SveInput  # noqa: E402


def cpu_ms(run: Callable[..., object], *args: object) -> float:
    """This thread's CPU time of ``run(*args)``, ms."""
    start = time.thread_time()
    run(*args)
    return (time.thread_time() - start) * 1e3


def before_fallback(inp: SveInput) -> tuple[list, list, np.ndarray, np.ndarray]:
    """(spans, the strips' Dark, image, variance) after steps 1-4, before the fallback, as ``adaptive`` makes them
    (float32 (H, W) image and variance)."""
    ky, kx = kernels(inp.pattern.shape)
    spans = adaptive._spans(inp, 3 * (max(len(ky), len(kx)) // 2), 64)
    frame = adaptive._frame_settings(inp, adaptive.noise_model(inp), ky, kx)
    image, variance = np.empty(inp.shape, np.float32), np.empty(inp.shape, np.float32)
    darks = []
    for start, top, bottom, stop in spans:
        crop = inp if (start, stop) == (0, inp.shape[0]) else inp.crop(slice(start, stop))
        keep = slice(top - start, bottom - start)
        pieces = adaptive._solve(crop, frame, True, False, keep, None)
        image[top:bottom], variance[top:bottom] = pieces[0][keep], pieces[2][keep]
        darks.append(pieces[4].rows(keep))
    return spans, darks, image, variance


def fallback_run(module, inp: SveInput, state: tuple) -> tuple[float, tuple[np.ndarray, np.ndarray]]:
    """CPU ms of ``module.wide_fallback`` on fresh copies of ``state`` (:func:`before_fallback`), and its image
    and variance."""
    spans, darks, image, variance = state
    darks = [module.Dark(d.weights, d.estimate.copy(), d.information.copy(), d.candidates.copy(), d.count)
             for d in darks]
    image, variance = image.copy(), variance.copy()
    ky, kx = kernels(inp.pattern.shape)
    ms = cpu_ms(module.wide_fallback, inp, spans, darks, image, variance, ky, kx, 1)
    return ms, (image, variance)


def load_revision(revision: str, directory: str) -> ModuleType:
    """adaptive/fallback.py of ``revision`` with the posterior.py it imports, both of that revision, imported from
    copies in ``directory`` (module names of their own)."""
    package = "svelive/reconstruction/methods/adaptive"
    for name in ("fallback", "posterior"):
        text = subprocess.run(["git", "-C", _CHECKOUT, "show", f"{revision}:{package}/{name}.py"],
                              check=True, capture_output=True, text=True).stdout
        text = text.replace("from svelive.reconstruction.methods.adaptive.posterior import",
                            "from posterior_compared import")
        with open(os.path.join(directory, f"{name}_compared.py"), "w") as file:
            file.write(text)
    sys.path.insert(0, directory)
    return importlib.import_module("fallback_compared")


def dim_frames(data: Path) -> list[tuple[str, np.ndarray, str, float]]:
    """(name, raw frame, pattern, the fallback's share) of every dim timing frame, largest share first."""
    frames = []
    for path in find_images(data):
        scene = load_scene(path)
        for pattern in PATTERNS:
            raw = timing_frame(scene, Condition(pattern, "dim"), 0)
            share = adaptive.path_shares(prepare(raw, pattern, BENCH_SENSOR))["wide"]
            frames.append((f"{path.stem} {pattern} dim", raw, pattern, share))
    return sorted(frames, key=lambda f: -f[3])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default="../shared/data/hdr")
    ap.add_argument("--frames", type=int, default=3, help="the frames with the largest shares timed")
    ap.add_argument("--repeats", type=int, default=9)
    ap.add_argument("--compare", metavar="REV", help="another revision's fallback, timed alternated with this one's")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    keep_freed_memory()
    with tempfile.TemporaryDirectory() as scratch:
        versions = {"this": fallback}
        if args.compare:
            versions["old"] = load_revision(args.compare, scratch)
        frames = dim_frames(Path(args.data))
        n = len(frames)
        chosen = sorted({*range(min(args.frames, n)), n // 2})
        print(f"# {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}; 1920x1200 dim bench frames, one thread, "
              f"CPU ms, median of {args.repeats} after a warm-up, versions alternated")
        for k in chosen:
            name, raw, pattern, share = frames[k]
            inp = prepare(raw, pattern, BENCH_SENSOR)
            state = before_fallback(inp)
            wide: dict[str, list[float]] = {v: [] for v in versions}
            whole: dict[str, list[float]] = {v: [] for v in versions}
            outputs = {}
            for _ in range(args.repeats + 1):
                for v, module in versions.items():
                    ms, outputs[v] = fallback_run(module, inp, state)
                    wide[v].append(ms)
                    adaptive.wide_fallback = module.wide_fallback
                    whole[v].append(cpu_ms(adaptive.run, inp))
            adaptive.wide_fallback = fallback.wide_fallback
            label = f"{name} ({'median' if k == n // 2 else f'rank {k + 1}/{n}'})"
            print(f"{label:40s} share {100 * share:5.1f} %: " + ", ".join(
                f"{v} fallback {np.median(wide[v][1:]):5.1f} / adaptive {np.median(whole[v][1:]):5.1f}"
                for v in versions), end="")
            if args.compare:
                same = all(np.array_equal(a, b) for a, b in zip(outputs["this"], outputs["old"]))
                diff = max(float(np.max(np.abs(a - b) / np.maximum(np.abs(b), 1e-30)))
                           for a, b in zip(outputs["this"], outputs["old"]))
                print(f"; same bits: {same} (largest relative difference {diff:.1e})", end="")
            print(flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
