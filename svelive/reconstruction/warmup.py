"""Kernel warm-up: compile, or load from numba's disk cache, every kernel a stream can run."""

from __future__ import annotations

from collections.abc import Iterable
from itertools import product

import numpy as np

from svelive.pattern import Pattern
from svelive.reconstruction.methods import METHODS
from svelive.reconstruction.stream import EXPOSURE_TIMINGS, Reconstructor


def warm_up(methods: Iterable[str] | None = None) -> None:
    """Compile, or load from numba's disk cache, every kernel a stream of these methods runs.

    A kernel compiles on its first call (about a second each on a fresh
    machine); a service or an image build calls this once so that no live
    frame waits for it. Runs a few tiny synthetic frames (without and with
    saturated pixels, which take different paths) through a temporal
    Reconstructor per method and kind of pattern,
    with ``mask`` and ``integration`` exposure timing (the latter runs the
    within-frame test, whose output variance is also computed), and the preview
    tone map. ``methods``: default every method but ``cubic`` (numpy only). The
    frames are uint16; other raw types are converted to float32 before any
    kernel, so they need nothing more.
    """
    from svelive.tonemap import ToneMapper  # only the preview uses it

    rng = np.random.default_rng(0)
    scene = rng.uniform(0, 200, (24, 32))  # still, so that frames after the first fuse with the history
    clean = [np.clip(rng.normal(scene, 3), 0, 4095).astype(np.uint16) for _ in range(3)]
    saturated = [frame.copy() for frame in clean]
    for frame in saturated:
        frame[:2, :4] = 4095
    nominal = Pattern.parse("1,4/16,64")
    # kernels take other paths for other tiles (1/1/8/8) and for calibrated per-pixel exposure maps
    patterns = [nominal, Pattern.parse("1/1/8/8"), nominal.with_pixel_map(nominal.exposure_map(scene.shape))]
    for method in methods if methods is not None else [m for m in METHODS if m != "cubic"]:
        for pattern, timing in product(patterns, EXPOSURE_TIMINGS):
            if timing == "integration" and pattern.pixel_map is not None:
                continue  # the within-frame test needs a nominal tile
            for frames in (clean, saturated):
                reconstructor = Reconstructor(pattern, method=method, white_level=4095, exposure_timing=timing)
                for frame in frames:
                    result = reconstructor.process(frame)
                result.variance  # noqa: B018 (computed on demand: the within-frame test's variance kernel)
    ToneMapper()(result.image, 0)
