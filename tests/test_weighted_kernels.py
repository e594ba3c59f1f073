"""The weighted method's compiled kernels against a plain-numpy statement of its formulas (module docstring)."""

import cv2
import numpy as np
import pytest

from svelive import Pattern, Sensor, simulate
from svelive.methods.base import binomial_kernel, censored_lower_bound, smooth, support_size
from svelive.reconstruct import prepare, run_method

SENSOR = Sensor.from_full_well(12, 10_000, 3)


def _reference(inp):
    """(image, lower_bound, variance) of the weighted method, whole frame, one numpy expression per formula."""
    f32 = np.float32
    th, tw = inp.pattern.shape
    window = (support_size(th), support_size(tw))
    ky, kx = binomial_kernel(window[0]), binomial_kernel(window[1])
    s, e, censored = inp.signal, inp.exposure, inp.censored
    gain, floor = f32(inp.sensor.effective_gain), f32(inp.sensor.floor_variance)

    # L0 = sum(s) / sum(e) over the uncensored pixels of the window
    exposure_sum = smooth(np.where(censored, f32(0), e), ky, kx)
    pilot = np.maximum(smooth(np.where(censored, f32(0), s), ky, kx) / np.maximum(exposure_sum, f32(1e-30)), f32(0))

    numerator, denominator, information = (np.zeros(inp.shape, f32) for _ in range(3))
    index = inp.pattern.level_index_map(inp.shape)
    for k, level in enumerate(inp.pattern.levels):
        mask = (index == k).astype(f32)
        share = smooth(mask, ky, kx)  # n_k
        effective = share * share / np.maximum(smooth(mask, ky * ky, kx * kx), f32(1e-12))  # n_eff,k
        interpolated = smooth(mask * s / e, ky, kx)  # n_k m_k
        # left out where the window holds a censored pixel of this level
        near = cv2.dilate((censored & (index == k)).view(np.uint8), np.ones(window, np.uint8),
                          borderType=cv2.BORDER_REFLECT_101).view(bool)
        weight = np.where(near, f32(0), f32(level * level) / (f32(level) * pilot / gain + floor))  # w_k / n_k
        numerator += weight * interpolated
        denominator += weight * share
        information += weight * effective

    usable = denominator > 0
    image = np.maximum(np.where(usable, numerator / np.where(usable, denominator, 1), pilot), f32(0))
    image = np.where(~usable & censored, np.maximum(image, s / e), image)  # a censored pixel: at least its bound
    variance = np.where(usable, 1 / np.where(usable, information, 1), (image + floor) / np.maximum(exposure_sum, 1e-30))
    lower = exposure_sum <= 0
    bound = censored_lower_bound(inp, window)
    return np.where(lower, bound, image), lower, np.where(lower, bound * bound, variance)


def _frame(pattern, shape, seed):
    """A textured scene whose bright blob saturates some exposures, censored only in the middle rows."""
    rng = np.random.default_rng(seed)
    h, w = shape
    top = 2500 / Pattern.parse(pattern).levels.max()  # the longest exposure reads up to 2500 DN outside the blob
    truth = cv2.GaussianBlur(rng.uniform(0.05 * top, top, shape).astype(np.float32), (0, 0), 1.5)
    yy, xx = np.mgrid[:h, :w]
    truth += 50 * top * np.exp(-((yy - h / 2) ** 2 / (0.01 * h * h) + (xx - w / 3) ** 2 / (0.02 * w * w)))
    return simulate(truth, pattern, SENSOR, seed=seed).raw


def _check(inp):
    image, lower, variance = _reference(inp)
    est = run_method(inp, "weighted", return_variance=True)
    np.testing.assert_array_equal(est.lower_bound, lower)
    # float32 rounding: the kernels order a few operations differently from this statement of the formulas
    np.testing.assert_allclose(est.image, image, rtol=1e-5, atol=1e-5 * float(image.max()))
    np.testing.assert_allclose(est.variance, variance, rtol=1e-5)
    plain = run_method(inp, "weighted")
    np.testing.assert_array_equal(plain.image, est.image)
    assert plain.variance is None


# 2x2, a 4-row tile and a 3x3 tile (its window misses a row of the tile at the frame's edges)
PATTERNS = ["1,4/16,64", "1/1/8/8", "1,2,4/8,16,32/64,128,256"]


@pytest.mark.parametrize("pattern", PATTERNS)
@pytest.mark.parametrize("shape", [(37, 41), (301, 50)])  # one strip, and strips with and without censored pixels
def test_kernels_agree_with_the_numpy_formulas(pattern, shape):
    inp = prepare(_frame(pattern, shape, seed=5), pattern, SENSOR)
    assert 0.005 < inp.censored.mean() < 0.5
    if shape[0] > 100:
        assert not inp.censored[:70].any()  # whole strips without censored pixels
    _check(inp)


@pytest.mark.parametrize("pattern", PATTERNS)
@pytest.mark.parametrize("shape", [(1, 1), (1, 9), (2, 7), (3, 5), (8, 1)])
def test_tiny_frames_agree_with_the_numpy_formulas(pattern, shape):
    # some levels have no pixel in any window here
    rng = np.random.default_rng(3)
    raw = rng.integers(0, 4096, shape).astype(np.uint16)
    _check(prepare(raw, pattern, SENSOR))


def test_saturated_and_black_frames_agree_with_the_numpy_formulas():
    for value in (0, 4095):
        _check(prepare(np.full((70, 9), value, np.uint16), "1,4/16,64", SENSOR))


def test_pixel_map_agrees_with_the_numpy_formulas():
    rng = np.random.default_rng(4)
    pattern = Pattern.parse("1,4/16,64")
    shape = (150, 40)
    pixel_map = (pattern.exposure_map(shape) * rng.uniform(0.8, 1.2, shape)).astype(np.float32)
    for brightest in (50, 200):  # without and with censored pixels
        raw = np.minimum(np.rint(pixel_map * rng.uniform(5, brightest, shape)), 4095).astype(np.uint16)
        inp = prepare(raw, pattern.with_pixel_map(pixel_map), SENSOR)
        assert inp.censored.any() == (brightest > 50)
        _check(inp)


def test_strips_on_threads_equal_one_thread():
    inp = prepare(_frame("1,4/16,64", (301, 50), seed=6), "1,4/16,64", SENSOR)
    one = run_method(inp, "weighted", return_variance=True)
    two = run_method(inp, "weighted", return_variance=True, workers=2)
    np.testing.assert_array_equal(one.image, two.image)
    np.testing.assert_array_equal(one.lower_bound, two.lower_bound)
    np.testing.assert_array_equal(one.variance, two.variance)
