"""The weighted method's compiled kernels against a plain-numpy statement of its formulas (module docstring)."""

import cv2
import numpy as np
import pytest

from svelive import Pattern, Sensor, simulate
from svelive.reconstruction.methods import weighted
from svelive.reconstruction.methods.base import SveInput, binomial_kernel, censored_lower_bound, smooth, support_size
from svelive.reconstruction.input import prepare
from svelive.reconstruction.single import run_method

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


PATTERNS = [
    # summed the polyphase way: 2x2, four levels; a checkerboard (a level on two phases); 2x1 and 1x2
    "1,4/16,64", "1,16/16,1", "1/16", "1,16",
    # the general way: a level on 3 of 4 phases, a 4-row tile, a 3x3 tile (its window misses a row
    # of the tile at the frame's edges)
    "1,1/1,4", "1/1/8/8", "1,2,4/8,16,32/64,128,256",
]


@pytest.mark.parametrize("pattern", PATTERNS)
@pytest.mark.parametrize("shape", [(37, 41), (301, 50)])  # one strip, and strips with and without censored pixels
def test_kernels_agree_with_the_numpy_formulas(pattern, shape):
    inp = prepare(_frame(pattern, shape, seed=5), pattern, SENSOR)
    assert 0.005 < inp.censored.mean() < 0.5
    if shape[0] > 100:
        assert not inp.censored[:70].any()  # whole strips without censored pixels
    _check(inp)


@pytest.mark.parametrize("pattern", PATTERNS)
@pytest.mark.parametrize("shape", [(1, 1), (1, 9), (2, 2), (2, 7), (3, 5), (7, 2), (8, 1)])
def test_tiny_frames_agree_with_the_numpy_formulas(pattern, shape):
    # some levels have no pixel in any window here
    rng = np.random.default_rng(3)
    raw = rng.integers(0, 4096, shape).astype(np.uint16)
    _check(prepare(raw, pattern, SENSOR))


@pytest.mark.parametrize("pattern", PATTERNS)
@pytest.mark.parametrize("shape", [(2, 2), (5, 3), (2, 9), (9, 2), (6, 7)])
def test_censored_edges_and_corners_agree_with_the_numpy_formulas(pattern, shape):
    rng = np.random.default_rng(8)
    raw = rng.integers(0, 4096, shape)
    raw[rng.random(shape) < 0.25] = 4095  # censored pixels of every level on every edge and corner
    _check(prepare(raw.astype(np.uint16), pattern, SENSOR))


def test_float_raw_and_inexact_exposures_agree_with_the_numpy_formulas():
    # exposures not powers of 2 and a non-integer raw: s / e and the sums round differently
    # from the numpy statement, by float32 rounding only
    raw = _frame("1,3/9,27", (150, 45), seed=9).astype(np.float32)
    raw += np.random.default_rng(9).uniform(-0.5, 0.5, raw.shape).astype(np.float32)
    _check(prepare(raw, "1,3/9,27", SENSOR))


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


@pytest.mark.parametrize("pattern, shape, polyphase", [
    ("1,4/16,64", (37, 41), True), ("1,16/16,1", (37, 41), True), ("1/16", (9, 1), True), ("1,16", (1, 9), True),
    ("4", (1, 1), True),
    ("1,4/16,64", (1, 9), False), ("1,4/16,64", (9, 1), False),  # one row or column: it reflects onto itself
    ("1/16", (1, 9), False), ("1,1/1,4", (37, 41), False), ("1/1/8/8", (37, 41), False),
    ("1,2,4/8,16,32/64,128,256", (37, 41), False),
])
def test_polyphase_sums_exactly_where_they_are_exact(pattern, shape, polyphase):
    assert weighted._level_layout(Pattern.parse(pattern), shape).polyphase == polyphase


# tiles of at most 2x2 on frames up to a few pixels wide, where they take the polyphase way
POLYPHASE = [(pattern, shape)
             for pattern in ["1,4/16,64", "64,1/16,4", "1,16/16,1", "1,1/16,16", "1/16", "1,16", "4", "4,4/4,4"]
             for shape in [(2, 2), (2, 5), (5, 2), (3, 3), (6, 7), (1, 6), (6, 1)]
             if weighted._polyphase(Pattern.parse(pattern), shape)]


@pytest.mark.parametrize("pattern, shape", POLYPHASE)
def test_polyphase_planes_are_the_levels_window_sums(pattern, shape):
    """Each plane times its scale is, at every pixel, the window sum of s over the level it names."""
    pattern = Pattern.parse(pattern)
    layout = weighted._level_layout(pattern, shape)
    assert layout.polyphase
    rng = np.random.default_rng(10)
    s = rng.uniform(0, 100, shape).astype(np.float32)
    s[rng.random(shape) < 0.2] = np.inf  # censored: makes the sum of its level +inf
    th, tw = pattern.shape
    ky, kx = binomial_kernel(support_size(th)), binomial_kernel(support_size(tw))
    index = pattern.level_index_map(shape)
    expected = np.stack([smooth(np.where(index == k, s, np.float32(0)), ky, kx) for k in range(len(pattern.levels))])
    planes = weighted._group_sums(weighted._neighbour_sums(s, pattern.shape), layout.groups, pattern.shape)
    phases = np.arange(shape[0]) % layout.exposures.shape[1]
    level = np.searchsorted(pattern.levels, layout.exposures[:, phases])  # the level each plane names
    for p, plane in enumerate(planes):
        np.testing.assert_allclose(plane * layout.scales[p], np.take_along_axis(expected, level[p:p + 1], 0)[0],
                                   rtol=1e-6, atol=1e-5)
    # every level with a pixel in the window is named by exactly one plane
    for k in range(len(pattern.levels)):
        present = smooth((index == k).astype(np.float32), ky, kx) > 0
        np.testing.assert_array_equal((level == k).sum(axis=0)[present], 1)


def test_strips_on_threads_equal_one_thread():
    inp = prepare(_frame("1,4/16,64", (301, 50), seed=6), "1,4/16,64", SENSOR)
    one = run_method(inp, "weighted", return_variance=True)
    two = run_method(inp, "weighted", return_variance=True, workers=2)
    np.testing.assert_array_equal(one.image, two.image)
    np.testing.assert_array_equal(one.lower_bound, two.lower_bound)
    np.testing.assert_array_equal(one.variance, two.variance)


def test_read_only_signal_gives_the_same_result():
    # the polyphase way sums the signal itself where a strip has no censored pixel
    inp = prepare(_frame("1,4/16,64", (301, 50), seed=11), "1,4/16,64", SENSOR)
    signal = inp.signal.copy()
    signal.setflags(write=False)
    frozen = SveInput(signal, inp.exposure, inp.censored, inp.pattern, inp.sensor, inp.integral)
    np.testing.assert_array_equal(run_method(frozen, "weighted").image, run_method(inp, "weighted").image)
