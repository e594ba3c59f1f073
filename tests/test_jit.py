"""The compiled kernels: warm_up covers every signature a live stream uses, so no live frame compiles."""

import importlib
import pkgutil
from itertools import product

import numba
import numpy as np

import svelive
from svelive import Camera, Pattern, Sensor
from svelive.reconstruction.stream import Reconstructor
from svelive.reconstruction.warmup import warm_up
from svelive.tonemap import ToneMapper


def kernels() -> dict[str, object]:
    """Every numba dispatcher defined in a svelive module, by qualified name."""
    found = {}
    for info in pkgutil.walk_packages(svelive.__path__, "svelive."):
        module = importlib.import_module(info.name)
        for name, value in vars(module).items():
            if isinstance(value, numba.core.dispatcher.Dispatcher) and value.py_func.__module__ == info.name:
                found[f"{info.name}.{name}"] = value
    return found


def test_warm_up_compiles_what_a_stream_runs():
    warm_up()
    found = kernels()
    assert len(found) >= 5, found.keys()  # the methods', the motion stage's and the tone map's kernels
    before = {name: len(k.signatures) for name, k in found.items()}  # 0 for kernels only other kernels call
    rng = np.random.default_rng(3)
    dark = rng.uniform(0, 1500, (160, 128))
    bright = dark.copy()
    bright[100:] *= 4  # the bottom strips saturate, the top ones do not
    nominal = Pattern.parse("1,4/16,64")
    patterns = [nominal, Pattern.parse("1/1/8/8"), nominal.with_pixel_map(nominal.exposure_map(dark.shape))]
    for method, pattern, scene in product(("adaptive", "weighted", "aggregate"), patterns, (dark, bright)):
        for dtype, white in ((np.uint16, 4095), (np.uint8, 255)):
            for timing in ("mask", "integration"):  # integration: the within-frame test too
                if timing == "integration" and pattern.pixel_map is not None:
                    continue
                reconstructor = Reconstructor(pattern, method=method, white_level=white, exposure_timing=timing)
                for moved in (0, 0, 0, 1, 40):  # fuse, then a small move, then the whole frame moves
                    noisy = rng.normal(np.roll(scene, moved, axis=1), 20) * white / 4095
                    result = reconstructor.process(np.clip(noisy, 0, white).astype(dtype))
                result.variance  # noqa: B018 (computed on demand)
                ToneMapper()(result.image, 0)
    reconstructor = Reconstructor("1,4/16,64", white_level=4095, exposure_timing="integration", temporal=False)
    for _ in range(2):
        result = reconstructor.process(np.clip(rng.normal(bright, 20), 0, 4095).astype(np.uint16))
    result.variance  # noqa: B018
    # the band refresh (the live service's monochrome default): bands skipped once the histories settle, pixels
    # reset in them on demand (a small move, then a large one), a frame estimated ahead of the one before it
    for pattern, scene in product(patterns[:2], (dark, bright)):
        for dtype, white in ((np.uint16, 4095), (np.uint8, 255)):
            reconstructor = Reconstructor(pattern, white_level=white, gain=0.5, read_noise=2.0, refresh=3)
            raws = [np.clip(rng.normal(np.roll(scene, moved, axis=1), 20) * white / 4095, 0, white).astype(dtype)
                    for moved in (0,) * 10 + (1, 40, 40)]
            for raw in raws[:-2]:
                result = reconstructor.process(raw)
            ahead = [reconstructor.estimate(raw) for raw in raws[-2:]]
            for estimated in ahead:
                result = reconstructor.fuse(estimated)
            assert reconstructor.last_partial["bands"] == 3
            result.variance  # noqa: B018
    # a small change in a settled band, no pixel saturated, as on the live demo's still view: its pixels take their
    # estimate on demand in cells (an atlas of patches: writable exposures beside the pattern's cached window sums)
    tall = rng.uniform(0, 1500, (200, 128))
    reconstructor = Reconstructor("1,4/16,64", white_level=4095, gain=1.0, read_noise=20.0, refresh=3)
    cells = 0
    for level in (0,) * 11 + (500, -500, 500):
        scene = tall.copy()
        scene[100:102, 60:62] += level
        scene[30:32, 90:92] += level
        reconstructor.process(np.clip(rng.normal(scene, 20), 0, 4095).astype(np.uint16))
        cells += reconstructor.last_partial.get("demand_cells", 0)
    assert cells > 0
    # the colour band refresh (``colour_refresh``, the service's colour streams): bands of the folded luminance, the
    # skipped rows' window mean by the per-pixel pass, pixels reset in skipped bands on demand (a small change, then
    # moves), a frame estimated ahead of the one before it; dual-ISO's 4-row tiles and 2x2 ones
    glare = tall.copy()
    glare[40:44, :8] = 8000  # saturated in every frame (a frame saturated all over never settles)
    for pattern, scene, (dtype, white) in product(("1/1/8/8", "1,4/16,64"), (tall, glare),
                                                  ((np.uint16, 4095), (np.uint8, 255))):
        camera = Camera.build(pattern, "RGGB", Sensor(8 if dtype == np.uint8 else 12, gain=1.0, read_noise=20.0))
        reconstructor = Reconstructor(camera, refresh=3, colour_refresh=True)
        raws = []
        for level, moved in [(0, 0)] * 11 + [(500, 0), (-500, 0), (0, 1), (0, 40), (0, 40)]:
            view = np.roll(scene, moved, axis=1)
            view[100:102, 60:62] += level
            raws.append(np.clip(rng.normal(view, 20) * white / 4095, 0, white).astype(dtype))
        skipped = demand = 0
        for raw in raws[:-2]:
            result = reconstructor.process(raw)
            last = reconstructor.last_partial or {}
            skipped += last.get("computed", 0) < last.get("bands", 0)
            demand += last.get("demand_px", 0)
        ahead = [reconstructor.estimate(raw) for raw in raws[-2:]]
        for estimated in ahead:
            result = reconstructor.fuse(estimated)
        assert skipped and demand, (pattern, skipped, demand)
        result.variance  # noqa: B018
    after = {name: len(k.signatures) for name, k in found.items()}
    assert after == before
