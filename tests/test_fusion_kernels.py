"""The motion stage's compiled kernels against the OpenCV/numpy formulations they replace (bit for bit)."""

from __future__ import annotations

import numpy as np
import pytest

from svelive import Pattern, Sensor, simulate
from svelive.core.camera import COLOUR_LAYOUTS, camera_for_raw
from svelive.reconstruction import numerics
from svelive.reconstruction.fusion import _paint_row
from svelive.reconstruction.input import prepare
from svelive.reconstruction.methods.base import binomial_kernel, smooth
from svelive.reconstruction.numerics import _confirmed, _symmetric_row, _widen, window_estimate

SENSOR = Sensor.from_full_well(12, 10_000, 3)


@pytest.mark.parametrize("length", [1, 2, 3, 4, 7, 64, 1923])
@pytest.mark.parametrize("squared", [False, True])
def test_symmetric_sums_as_opencv(length, squared):
    """Along rows up to INLINE_TAPS[1] taps, down columns up to INLINE_TAPS[0]."""
    rng = np.random.default_rng(length)
    one = np.ones(1, np.float32)
    x = (rng.random((1, length), dtype=np.float32) * 4000 - 100).astype(np.float32)
    out = np.empty(length, np.float32)
    for taps in range(1, numerics.INLINE_TAPS[1] + 1, 2):
        k = binomial_kernel(taps)
        k = k * k if squared else k
        _symmetric_row(x[0], k, out)
        assert np.array_equal(out, smooth(x, one, k)[0])
    for taps in range(1, numerics.INLINE_TAPS[0] + 1, 2):
        k = binomial_kernel(taps)
        k = k * k if squared else k
        _symmetric_row(x[0], k, out)
        assert np.array_equal(out, smooth(x.T.copy(), k, one)[:, 0])


def _input(shape, pattern="1,4/16,64", cfa=None, seed=0, bright=1.0):
    rng = np.random.default_rng(seed)
    scene = np.float32(300 * bright) * rng.random((shape[0], shape[1]) + ((3,) if cfa else ()), dtype=np.float32)
    scene[: shape[0] // 3] *= np.float32(40)  # plenty of censored readings
    raw = simulate(scene, pattern, SENSOR, cfa=cfa, seed=seed).raw
    camera = camera_for_raw(raw, Pattern.parse(pattern), cfa=cfa, white_level=SENSOR.white_level, gain=SENSOR.gain,
                            read_noise=SENSOR.read_noise)
    return prepare(raw, camera)


@pytest.mark.parametrize("shape", [(1, 5), (3, 4), (7, 9), (37, 61), (130, 97)])
@pytest.mark.parametrize("pattern", ["1,4/16,64", "1,8", "1/4/16", "1/1/8/8", "1,2,4,8/16,32,64,128",
                                     "1/2/4/8/16/32"])
def test_window_estimate_inline_is_the_opencv_one(shape, pattern, monkeypatch):
    inp = _input(shape, pattern, seed=shape[0])
    image = np.full(shape, 7.0, np.float32)
    variance = np.full(shape, 3.0, np.float32)
    inline = window_estimate(inp, image, variance, strip_rows=16)
    monkeypatch.setattr(numerics, "INLINE_TAPS", (0, 0))  # the OpenCV windows
    reference = window_estimate(inp, image, variance, strip_rows=16)
    for a, b in zip(inline, reference):
        assert np.array_equal(a, b)


@pytest.mark.parametrize("layout", ["assorted-4x4", "dual-iso", "quad-bayer", "column-bayer"])
def test_window_estimate_inline_is_the_opencv_one_colour(layout, monkeypatch):
    from svelive.reconstruction import colour
    from svelive.reconstruction.methods import DEFAULT_METHOD
    from svelive.reconstruction.single import method_spec

    pattern, cfa = COLOUR_LAYOUTS[layout]
    inp = _input((48, 40), pattern, cfa=cfa)
    lum = colour.joint(inp, method_spec(DEFAULT_METHOD), rgb=False).luminance_input
    image = np.full(lum.shape, 7.0, np.float32)
    variance = np.full(lum.shape, 3.0, np.float32)
    inline = window_estimate(lum, image, variance, strip_rows=8)
    monkeypatch.setattr(numerics, "INLINE_TAPS", (0, 0))
    reference = window_estimate(lum, image, variance, strip_rows=8)
    for a, b in zip(inline, reference):
        assert np.array_equal(a, b)


@pytest.mark.parametrize("pattern", ["1,4/16,64", "1/1/8/8"])  # (the second: numerics._window_strip_column)
def test_window_estimate_without_uncensored_readings_takes_the_method(pattern):
    inp = _input((12, 12), pattern, bright=1e6)  # every reading censored
    assert inp.censored.all()
    image = np.full(inp.shape, 5.0, np.float32)
    variance = np.full(inp.shape, 2.0, np.float32)
    level, noise = window_estimate(inp, image, variance)
    assert np.array_equal(level, image) and np.array_equal(noise, variance)


@pytest.mark.parametrize("widen", [0, 1, 2])
@pytest.mark.parametrize("density", [0.001, 0.05, 0.6])
def test_moving_rows_is_confirmation_then_widening(widen, density):
    rng = np.random.default_rng(int(density * 1000) + widen)
    flagged = rng.random((40, 53)) < density
    flagged[10, :] = False
    flagged[20, 5:7] = True  # a confirmed pair
    first, rows = 6, 28
    motion = np.zeros((rows, 53), bool)
    counts = np.count_nonzero(flagged, axis=1).astype(np.intp)
    count = sum(_paint_row(flagged, counts, r, len(flagged), first, widen, motion) for r in range(len(flagged)))
    expected = _widen(_confirmed(flagged), widen)[first:first + rows]
    assert np.array_equal(motion, expected)
    assert count == np.count_nonzero(expected)


@pytest.mark.parametrize("window", [(3, 3), (5, 1), (5, 3), (1, 3)])
@pytest.mark.parametrize("shape", [(1, 4), (6, 9), (70, 33)])
def test_detail_rows_is_the_window_mean_then_the_detail_pass(window, shape):
    from svelive.jit import flat
    from svelive.reconstruction.fusion import _detail_pass, _detail_rows, _DetailStep

    rng = np.random.default_rng(window[0] * 100 + shape[0])
    ky, kx = (binomial_kernel(n) for n in window)
    evidence = (rng.random(shape, dtype=np.float32) * 3).astype(np.float32)
    evidence[0, 0] = 0
    fused = (rng.random(shape, dtype=np.float32) * 100).astype(np.float32)
    own = (fused + rng.normal(0, 5, shape)).astype(np.float32)
    reset = rng.random(shape) < 0.2
    threshold = np.float32(1.4)
    expected = np.empty(shape, np.float32)
    _detail_pass(*flat(smooth(evidence, ky, kx), fused, own, reset, expected), threshold, True)
    along = np.empty(shape, np.float32)
    for r in range(shape[0]):
        _symmetric_row(evidence[r], kx, along[r])
    out = np.empty(shape, np.float32)
    for first in range(0, shape[0], 4):  # in strips of 4 rows
        _detail_rows(along, first, min(first + 4, shape[0]), _DetailStep(True, kx, ky, threshold, True), fused, own,
                     reset, out)
    assert np.array_equal(out, expected)


@pytest.mark.parametrize("pattern", ["1,4/16,64", "1/4/16/64", "1,2,4,8/16,32,64,128"])
@pytest.mark.parametrize("shape", [(5, 9), (41, 33), (130, 70)])
def test_fusion_detail_in_the_update_is_the_detail_pass(pattern, shape):
    """The update sharpens the rows whose detail window lies within its strip; strips of one row
    leave every row to the detail pass (_detail_rows, tested above): the same output either way,
    on one thread and on two, the within-frame finding applied alike."""
    from svelive.reconstruction.config import MotionConfig
    from svelive.reconstruction.consistency import exposure_consistency
    from svelive.reconstruction.fusion import FrameEstimate, fuse
    from svelive.reconstruction.single import estimate_variance, run_method
    from svelive.reconstruction.stream import own_reading_rows

    config = MotionConfig()
    tile = Pattern.parse(pattern).shape
    rows = own_reading_rows(Pattern.parse(pattern), shape, SENSOR)
    scene = np.float32(300) * np.random.default_rng(1).random(shape, dtype=np.float32)
    scene[: shape[0] // 3] *= np.float32(40)  # censored readings
    scene[shape[0] // 2:, : shape[1] // 4] = 0  # where the read noise decides
    camera = camera_for_raw(np.zeros(1, np.uint16), Pattern.parse(pattern), white_level=SENSOR.white_level,
                            gain=SENSOR.gain, read_noise=SENSOR.read_noise)
    states = {}
    for seed in range(4):
        inp = prepare(simulate(scene, pattern, SENSOR, seed=seed).raw, camera)  # a still scene, new noise
        est = run_method(inp, "weighted", return_variance=True)
        variance = estimate_variance(est, inp)
        frame = FrameEstimate(est.image, variance, est.lower_bound, inp.censored, inp.signal, *rows)
        results = {}
        for strip_rows, workers in ((1, 1), (2, 1), (3, 2), (7, 1), (16, 2), (64, 1), (1000, 1)):
            for within in (False, True):
                found = exposure_consistency(est.image, variance, inp, config) if within else None
                results[strip_rows, workers, within] = fuse(states.get(within), frame, config, tile, found,
                                                            workers=workers, strip_rows=strip_rows)
        for within in (False, True):
            reference = results[1, 1, within]
            for key, fused in results.items():
                if key[2] == within:
                    for name in ("image", "motion", "history"):
                        assert np.array_equal(getattr(fused, name), getattr(reference, name)), (key, name)
            states[within] = reference.state
    assert (reference.history < 1).any()  # pixels with history: the detail step ran


@pytest.mark.parametrize("pattern", ["1,4/16,64", "1/4/16/64", "1,2,4,8/16,32,64,128"])
@pytest.mark.parametrize("widen", [0, 1, 2])
def test_fusion_masks_are_the_whole_frame_test(pattern, widen):
    """The strips' one pass (test, confirmation and widening, update) gives the whole-frame masks:
    flagged where the noise test fires and the pixel is stable (or a lower bound proves motion),
    unstable within a tile window of a censoring change (OpenCV's dilation) or at a bound; motion
    the flagged pixels with a flagged 8-neighbour, widened; reset (weight 1) where flagged,
    unstable or moving."""
    from svelive.reconstruction.config import MotionConfig
    from svelive.reconstruction.fusion import FrameEstimate, fuse
    from svelive.reconstruction.numerics import _confirmed, _grow
    from svelive.reconstruction.stream import own_reading_rows

    shape = (77, 45)
    config = MotionConfig(widen=widen, compensate_illumination=False)
    tile = Pattern.parse(pattern).shape
    window = tuple(n + 1 if n % 2 == 0 else n for n in tile)
    rng = np.random.default_rng(widen)
    scene = np.float32(200) * rng.random(shape, dtype=np.float32)
    scene[20:30, 5:40] = 3000  # readings around the censor level: their censoring changes with the noise
    moved = scene.copy()
    moved[50:60, 10:20] = 900  # an object appears
    camera = camera_for_raw(np.zeros(1, np.uint16), Pattern.parse(pattern), white_level=SENSOR.white_level,
                            gain=SENSOR.gain, read_noise=SENSOR.read_noise)
    rows = own_reading_rows(Pattern.parse(pattern), shape, SENSOR)
    frames = []
    for seed, radiance in enumerate((scene, moved)):
        inp = prepare(simulate(radiance, pattern, SENSOR, seed=seed).raw, camera)
        image = np.where(inp.censored, np.float32(SENSOR.white_level), inp.signal * inp.exposure ** -1)
        image = smooth(image.astype(np.float32), *(binomial_kernel(n) for n in window))
        variance = (image / np.float32(SENSOR.effective_gain) + np.float32(4)).astype(np.float32)
        bound = inp.censored & (rng.random(shape) < 0.5)
        frames.append(FrameEstimate(image, variance, bound, inp.censored, inp.signal, *rows))
    first, second = frames
    state = fuse(None, first, config, tile).state
    changed = first.censored != second.censored
    assert changed.any()
    grown = _grow(changed, window)
    d = second.image - state.mean
    flagged = d * d * np.float32(1 / config.temporal_sigmas ** 2) > (state.weight + np.float32(1)) * second.variance
    proven = flagged & (second.bound != state.bound) & ((second.image > state.mean) == second.bound)
    unstable = grown | second.bound | state.bound
    flagged = (flagged & ~unstable) | proven
    motion = _widen(_confirmed(flagged), widen)
    assert motion.any() and (flagged & ~motion).any()
    for strip_rows, workers in ((1, 1), (4, 2), (9, 1), (64, 1)):
        fused = fuse(state, second, config, tile, workers=workers, strip_rows=strip_rows)
        assert np.array_equal(fused.motion, motion)
        assert np.array_equal(fused.history == 1, flagged | unstable | motion)
