"""The adaptive method's compiled kernels against a plain-numpy statement of its formulas (module docstring)."""

import dataclasses
import math

import cv2
import numpy as np
import pytest

from svelive import Pattern, Sensor, simulate
from svelive.jit import flat
from svelive.reconstruction.methods import adaptive
from svelive.reconstruction.methods.adaptive import censoring, evidence, fallback, parameters, posterior, strip_pass
from svelive.reconstruction.methods.base import (binomial_kernel, censored_lower_bound, fill_lower_bounds, reflect_101,
                                                  smooth, true_positions)
from svelive.reconstruction.input import prepare
from svelive.reconstruction.single import run_method

SENSOR = Sensor.from_full_well(12, 10_000, 3)


def _reference(inp):
    """(image, lower_bound, variance) of the adaptive method, whole frame, one numpy expression per formula."""
    f32 = np.float32
    ky, kx = parameters.kernels(inp.pattern.shape)
    window = (len(ky), len(kx))
    centre = f32(ky[len(ky) // 2] * kx[len(kx) // 2])
    kernel_square = f32((ky * ky).sum() * (kx * kx).sum())
    tiny = f32(parameters.TINY)
    s, e, censored = inp.signal, inp.exposure, inp.censored
    x = s / e
    e_valid = np.where(censored, f32(0), e)

    # pilot L0 = sum s / sum e over the uncensored readings of the window without the pixel; w = 1 / v at L0
    # (0 for censored readings), with the noise model floored by the frame's evidence
    s_valid = np.where(censored, f32(0), s)
    exposure_sum = smooth(e_valid, ky, kx)
    pilot = np.maximum((smooth(s_valid, ky, kx) - centre * s_valid)
                       / np.maximum(exposure_sum - centre * e_valid, tiny), f32(0))
    gain_inv, floor = (f32(v) for v in evidence.noise_model(inp))
    w = e * e_valid / (pilot * e * gain_inv + floor)

    # m: neighbours without the pixel itself, leaving out the dark side of an edge
    lowest_censored = cv2.erode(np.where(censored, e, f32(parameters.BIG)), np.ones(window, np.uint8),
                                borderType=cv2.BORDER_REFLECT_101)
    wn = np.where(lowest_censored <= e, f32(0), w)
    sum_w = np.maximum(smooth(wn, ky, kx) - centre * wn, tiny)
    wx = wn * x
    m = (smooth(wx, ky, kx) - centre * wx) / sum_w
    var_m = kernel_square / sum_w

    # b^2: residual excess over its noise, weights q = 1 / (v_p + v_m)^2, shrunk by CONTRAST_SIGMA standard errors
    var_r = f32(1) / np.maximum(w, tiny) + var_m
    q = f32(1) / (var_r * var_r)
    sum_q = np.maximum(smooth(q, ky, kx), tiny)
    standard_error = np.sqrt(f32(2) * kernel_square / sum_q)
    bias2 = np.maximum(smooth(q * ((x - m) ** 2 - var_r), ky, kx) / sum_q
                       - f32(parameters.CONTRAST_SIGMA) * standard_error, f32(0))
    # at least the pixel's own residual's excess beyond OWN_SIGMA deviations
    own_excess = (x - m) ** 2 - f32(strip_pass.OWN_SIGMA ** 2) * var_r
    bias2 = np.maximum(bias2, own_excess)

    # L^ = (x / v_p + m / (v_m + b^2)) / (1 / v_p + 1 / (v_m + b^2)), then exp(E[log L]) of N(L^, 1 / total) on L >= 0
    weight_m = f32(1) / (var_m + bias2)
    total = w + weight_m
    estimate = (w * x + weight_m * m) / total
    # where the own excess is positive, the reading's information in total at the lower of the pilot's level and L^
    at_level = e * e / (np.maximum(estimate, f32(0)) * e * gain_inv + floor)
    total = total + np.where((own_excess > 0) & (w > 0), np.maximum(at_level - w, f32(0)), f32(0))
    image = _nonnegative(estimate, total)
    # every reading of the window at raw 0: 0
    bottom = cv2.erode((s <= -inp.sensor.black_level).astype(np.uint8), np.ones(window, np.uint8),
                       borderType=cv2.BORDER_REFLECT_101).astype(bool)
    image = np.where(bottom, f32(0), image)
    variance = f32(1) / total

    # censored pixels: plain mean of the consistent uncensored neighbours, at least the own bound
    lower = exposure_sum <= 0
    reach = x + f32(parameters.CONSISTENT_SIGMA) * np.sqrt(f32(1) / np.maximum(w, tiny))
    for level in inp.pattern.levels:
        at = censored & (e == f32(level))
        consistent = ((w > 0) & (reach >= f32(inp.sensor.censor_level / level))).astype(f32)
        count = smooth(consistent, ky, kx)
        mean = np.maximum(smooth(consistent * x, ky, kx) / np.maximum(count, tiny), x)
        image = np.where(at, mean, image)
        lower |= at & (count <= 0)
    bound = censored_lower_bound(inp, window)
    image, variance = np.where(lower, bound, image), np.where(lower, bound * bound, variance)

    # the wide fallback where the result cannot tell the level from 0
    candidates = (((estimate <= 0) | (estimate * estimate * total < f32(parameters.CONTRAST_SIGMA ** 2)))
                  & (image > 0) & ~censored & ~lower)
    estimate, total, changed = _wide_reference(estimate, total, wn, x, censored, candidates, window)
    image = np.where(changed, _nonnegative(estimate, total), image)
    return image, lower, np.where(changed, f32(1) / total, variance)


def _wide_reference(estimate, information, wn, x, flags, active, window):
    """The wide fallback (fallback.wide_fallback) in numpy: (estimate, information, changed), float32 (H, W)."""
    f32, tiny = np.float32, np.float32(parameters.TINY)
    h, width = wn.shape
    by, bx = window
    changed = np.zeros_like(active)
    box = lambda a: cv2.boxFilter(a, cv2.CV_32F, (bx, by), normalize=False,  # noqa: E731
                                  borderType=cv2.BORDER_REFLECT_101)
    for _ in range(fallback.WIDE_SCALES):
        if 3 * by > h or 3 * bx > width:
            break
        block_w = box(wn)
        means = np.where(block_w > tiny, box(wn * x) / np.maximum(block_w, tiny), f32(0))
        means = np.where(box(flags.astype(f32)) > 0.5, f32(np.nan), means)
        rows, cols = np.arange(h), np.arange(width)
        blocks = [(block_w[np.ix_(_reflect(rows + dy * by, h), _reflect(cols + dx * bx, width))],
                   means[np.ix_(_reflect(rows + dy * by, h), _reflect(cols + dx * bx, width))])
                  for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx]
        sum_w, sum_wx, count, bad = f32(0), f32(0), f32(0), np.zeros_like(active)
        for bw, bm in blocks:
            sum_w = sum_w + np.where(bw > tiny, bw, f32(0))
            sum_wx = sum_wx + np.where(bw > tiny, bw * bm, f32(0))
            count = count + (bw > tiny).astype(f32)
            bad |= np.isnan(bm)
        mean = sum_wx / np.maximum(sum_w, tiny)
        chi2 = f32(0)
        for bw, bm in blocks:
            chi2 = chi2 + np.where(bw > tiny, bw * (bm - mean) ** 2, f32(0))
        dof = count - f32(1)
        sigmas = f32(parameters.CONTRAST_SIGMA)
        bias2 = np.maximum(chi2 - dof - sigmas * np.sqrt(f32(2) * dof), f32(0)) / sum_w
        weight = f32(1) / (f32(1) / sum_w + bias2)
        go = active & ~bad & (count >= 2)
        t = information + weight
        value = (estimate * information + mean * weight) / t
        estimate, information = np.where(go, value, estimate), np.where(go, t, information)
        changed |= go
        active = go & (bias2 <= 0) & ((estimate <= 0) | (estimate * estimate * information < sigmas * sigmas))
        by, bx = 3 * by, 3 * bx
    return estimate, information, changed


def _reflect(index, n):
    """Indices reflected into [0, n) as OpenCV's BORDER_REFLECT_101 (once is enough here)."""
    index = np.abs(index)
    return np.where(index >= n, 2 * (n - 1) - index, index)


def _nonnegative(estimate, information):
    """sigma g(z), g = b(z) P(u) (posterior.posterior_polynomial) below POSTERIOR_HIGH, the estimate above."""
    sigma = 1 / np.sqrt(information.astype(np.float64))
    z = estimate / sigma
    base, u = posterior.posterior_base(z)
    inside = sigma * base * np.polynomial.polynomial.polyval(u, posterior.posterior_polynomial().astype(np.float64))
    return np.where(z >= posterior.POSTERIOR_HIGH, estimate, inside).astype(np.float32)


def test_posterior_against_numerical_integration():
    """g(z) = exp(E[log L]) of the unit normal around z restricted to L > 0, by the trapezoid rule on a fine log
    grid: the table, and the polynomial the kernel evaluates (within 1e-3), deep below 0 up to POSTERIOR_HIGH,
    where it meets the estimate itself (within 1e-3)."""
    table = posterior.posterior_table()
    level = np.geomspace(1e-14, 80, 400_001)
    for z in (-20.0, -6.0, -2.0, 0.0, 1.5, 4.0, 12.0):  # on the table's grid
        density = np.exp(-0.5 * (level - z) ** 2 + 0.5 * min(z, 0) ** 2)
        expected = np.exp(np.trapezoid(np.log(level) * density, level) / np.trapezoid(density, level))
        base, u = posterior.posterior_base(np.array(z))
        fitted = base * np.polynomial.polynomial.polyval(u, posterior.posterior_polynomial().astype(np.float64))
        assert fitted == pytest.approx(expected, rel=1e-3), z
        got = table[int(round((z - posterior.POSTERIOR_LOW) / posterior.POSTERIOR_STEP))]
        assert got == pytest.approx(expected, rel=1e-4), z
    assert table[-1] == pytest.approx(posterior.POSTERIOR_HIGH, rel=1e-3)
    base, u = posterior.posterior_base(np.array(-300.0))  # the exponential tail
    tail = base * np.polynomial.polynomial.polyval(u, posterior.posterior_polynomial().astype(np.float64))
    assert tail == pytest.approx(posterior.TAIL / 300, rel=1e-3)


def test_posterior_table_in_chunks_is_the_whole_grid_at_once(monkeypatch):
    """The table integrated POSTERIOR_CHUNK rows of z at a time is bit for bit the whole grid in one pass, and what
    it allocates through numpy (malloc's heap, traced) stays below one whole-grid array (a process's first frame
    computes it: five such arrays of 85 MB set the service's peak resident memory)."""
    import tracemalloc

    compute = posterior.posterior_table.__wrapped__  # not the cached table
    tracemalloc.start()
    try:
        chunked = compute()
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    whole_grid_array = chunked.size * 12000 * 8  # (rows of z, 12000 values of u) float64
    assert peak < whole_grid_array
    monkeypatch.setattr(posterior, "POSTERIOR_CHUNK", chunked.size)
    whole = compute()
    assert np.array_equal(chunked, whole)
    assert np.array_equal(chunked, posterior.posterior_table())


@pytest.mark.parametrize("share", [0.0, 0.01, 0.06, 0.07, 0.19, 0.2, 0.3, 0.49, 0.5, 0.8, 1.0])
def test_posterior_at_is_the_posterior_of_the_whole_array_where_changed(share):
    """posterior_at (rows packed or taken whole, by the share of their pixels changed) gives, at the changed
    pixels, bit for bit what nonnegative gives on the whole arrays, and 1 / information as the variance; the
    other pixels keep their values. Rows of every share around DENSE_CHANGED, scattered pixels, odd width."""
    rng = np.random.default_rng(int(share * 100))
    shape = (40, 301)
    estimate = rng.normal(0, 3, shape).astype(np.float32)
    estimate[:, :20] *= 100  # some far beyond POSTERIOR_HIGH deviations
    information = rng.uniform(0.05, 20, shape).astype(np.float32)
    changed = rng.random(shape) < share
    changed[::7] = rng.random((len(changed[::7]), shape[1])) < rng.uniform(0, 1, (len(changed[::7]), 1))
    whole = estimate.copy()
    posterior.nonnegative(*flat(whole, estimate, information), posterior.posterior_polynomial())
    for with_variance in (True, False):
        image, variance = np.full(shape, -1, np.float32), np.full(shape, -2, np.float32)
        posterior.posterior_at(changed, estimate, information, image, posterior.posterior_polynomial(),
                               variance if with_variance else np.empty((0, 0), np.float32))
        np.testing.assert_array_equal(image, np.where(changed, whole, np.float32(-1)))
        np.testing.assert_array_equal(variance, np.where(changed & with_variance, np.float32(1) / information,
                                                         np.float32(-2)))


@pytest.mark.parametrize("rx", [0, 1, 2, 3])
@pytest.mark.parametrize("size", [1, 2, 3, 6, 7, 301])
def test_row_least_is_the_least_censored_exposure_around(rx, size):
    """strip_pass._row_least: the least exposure of the censored readings within rx columns (BIG where none), borders
    reflect-101, as OpenCV's erosion gives it, on rows shorter and longer than the window."""
    rng = np.random.default_rng(10 * size + rx)
    exposure = rng.uniform(1, 64, size).astype(np.float32)
    for share in (0.0, 0.1, 0.5, 1.0):
        censored = rng.random(size) < share
        out = np.empty(size, np.float32)
        strip_pass._row_least(exposure, censored, rx, np.empty(size, np.float32), out)
        values = np.where(censored, exposure, np.float32(parameters.BIG))[None]
        expected = values[0] if size < 2 else cv2.erode(values, np.ones((1, 2 * rx + 1), np.uint8),
                                                         borderType=cv2.BORDER_REFLECT_101)[0]
        np.testing.assert_array_equal(out, expected)


@pytest.mark.parametrize("share", [0.0, 0.002, 0.02, 0.2, 1.0])
@pytest.mark.parametrize("size", [1, 7, 64, 301, 1920])
def test_nonnegative_on_runs_is_the_whole_row(share, size):
    """strip_pass._nonnegative_runs (nonnegative on the runs of columns holding a pixel near 0) gives bit for bit
    what nonnegative gives on the whole row: pixels near 0 scattered, in clumps, at the row's ends, none; rows of
    whole words of flags, of whole runs, and neither."""
    rng = np.random.default_rng(size + int(share * 1000))
    coefficients = posterior.posterior_polynomial()
    for clumped in (False, True):
        estimate = rng.uniform(50, 500, size).astype(np.float32)  # beyond POSTERIOR_HIGH deviations (information >= 1)
        near = rng.random(size) < share
        if clumped:
            near = np.convolve(near, np.ones(9), "same")[:size] > 0
        if share > 0:
            near[[0, -1]] = True
        estimate[near] = rng.normal(0, 5, np.count_nonzero(near))
        information = rng.uniform(1, 20, size).astype(np.float32)
        whole, runs = estimate.copy(), estimate.copy()
        posterior.nonnegative(whole, estimate, information, coefficients)
        strip_pass._nonnegative_runs(runs, estimate, information, coefficients, np.empty(size, bool))
        np.testing.assert_array_equal(runs, whole)
        assert np.array_equal(whole != estimate, near & (whole != estimate))  # it changes only pixels near 0
        assert share == 0 or not np.array_equal(whole, estimate)


@pytest.mark.parametrize("pattern", ["1,4/16,64", "1/1/8/8"])
def test_noise_floor_from_the_frame(pattern):
    """The floor variance the method uses follows the frame's read noise whatever the sensor says, and the
    kernel's pairs agree with a numpy statement of them."""
    rng = np.random.default_rng(2)
    truth = cv2.GaussianBlur(rng.uniform(0.5, 3, (200, 200)).astype(np.float32), (0, 0), 3)  # dark: read noise
    true = Sensor(12, 64.0, 4095.0, 2.5, 2.0)
    raw = simulate(truth, pattern, true, seed=1).raw
    for factor in (0.5, 1.0, 2.0):
        told = Sensor(12, 64.0, 4095.0, 2.5, 2.0 * factor)
        inp = prepare(raw, pattern, told)
        gain_inv, floor = evidence.noise_model(inp)
        assert gain_inv == pytest.approx(1 / 2.5)
        assert floor == pytest.approx(true.floor_variance, rel=0.2), factor
    # the kernels against a numpy statement: integer readings (their differences' lattice), and the same readings
    # as floats (the normalised squared differences' fixed point)
    inp = prepare(raw, pattern, true)
    assert inp.integral
    g, f = 1 / true.gain, true.floor_variance
    assert evidence.floor_evidence(inp, g, f) == pytest.approx(_floor_reference(inp, g, f), rel=2e-3)
    inp = prepare(raw.astype(np.float32), pattern, true)
    assert not inp.integral
    assert evidence.floor_evidence(inp, g, f) == pytest.approx(_floor_reference(inp, g, f), rel=1e-4)


@pytest.mark.parametrize("pattern", ["1,4/16,64", "1/1/8/8"])
@pytest.mark.parametrize("read, gain, black", [(0.6, 10.0, 64), (1.0, 2.5, 64), (2.7, 2.5, 64), (2.7, 10.0, 0),
                                               (8.0, 2.5, 64)])
def test_noise_floor_of_integer_readings(pattern, read, gain, black):
    """Integer readings' floor from a dark frame without texture (a gentle ramp, each exposure's shot part at most
    the floor) is the true one within a few %: matched as continuous readings (chi-square(1)'s quantile), the
    lattice of their differences made it 0.19 of the truth at 0.6 DN read noise, about 0.65 at 2.7 DN, 3.5 times it at
    1 DN on 1/1/8/8."""
    true = Sensor(12, float(black), 4095.0, gain, read)
    top = gain * true.floor_variance / float(Pattern.parse(pattern).levels.max())
    low = 4 * np.sqrt(true.floor_variance) if black == 0 else 0.0  # clear of the clipping guard at a black level 0
    radiance = low + top * np.linspace(0, 1, 1024, dtype=np.float32) * np.ones((128, 1), np.float32)
    inp = prepare(simulate(radiance, pattern, true, seed=1).raw, pattern, true)
    assert evidence.noise_model(inp)[1] == pytest.approx(true.floor_variance, rel=0.06)


def _floor_reference(inp, g, f):
    """floor_evidence in numpy: the lattice of integer readings' differences (not folded), else the fixed point of
    the normalised squared differences' quantile."""
    f32 = np.float32
    tw = inp.period[1]
    rows = np.unique(np.linspace(0, inp.shape[0] - 1, evidence.EVIDENCE_ROWS).round().astype(int))
    s, e, c = inp.signal[rows], inp.exposure[rows], inp.censored[rows]
    lowest = f32(-inp.sensor.black_level + evidence.EVIDENCE_CLIP_SIGMA * np.sqrt(f))
    if not inp.integral:
        s, e = s.astype(np.float64), e.astype(np.float64)
        radiance = np.maximum((s[:, :-tw] + s[:, tw:]) / (e[:, :-tw] + e[:, tw:]), 0)
        shot = radiance * g * (1 / e[:, :-tw] + 1 / e[:, tw:])
        k = 1 / e[:, :-tw] ** 2 + 1 / e[:, tw:] ** 2
        square = (s[:, :-tw] / e[:, :-tw] - s[:, tw:] / e[:, tw:]) ** 2
        keep = (f * k > shot) & (s[:, :-tw] > lowest) & (s[:, tw:] > lowest) & ~c[:, :-tw] & ~c[:, tw:]
        level = f
        for _ in range(evidence.EVIDENCE_ITERATIONS):
            ratio = np.sort(square[keep] / (shot[keep] + level * k[keep]))
            level *= ratio[int(evidence.EVIDENCE_QUANTILE * (ratio.size - 1))] / evidence.CHI2_1_AT_QUANTILE
        return level / f
    w = s.shape[1]
    pair = [slice(tw, w - 2 * tw), slice(2 * tw, w - tw)]  # i, j = i + tw
    outer = [slice(0, w - 3 * tw), slice(3 * tw, w)]  # i - tw, j + tw
    ends = s[:, outer[0]] + s[:, outer[1]]
    level = ends / (e[:, outer[0]] + e[:, outer[1]])
    ei, ej = e[:, pair[0]], e[:, pair[1]]
    shot = np.maximum(level, f32(0)) * f32(g) * (f32(1) / ei + f32(1) / ej)
    keep = (f32(f) * (f32(1) / (ei * ei) + f32(1) / (ej * ej)) > shot) & (ends > lowest + lowest)
    for part in pair + outer:
        keep &= ~c[:, part]
    difference = np.abs(s[:, pair[0]] - s[:, pair[1]])[keep].astype(np.float64)
    total = (s[:, pair[0]] + s[:, pair[1]])[keep].astype(np.float64) * g  # the pairs' shot parts plus noise
    span = evidence.LATTICE_SPAN * (np.sort(difference)[int(evidence.EVIDENCE_QUANTILE * (difference.size - 1))] + 1)
    tent = np.mean(np.maximum(span - difference, 0))

    def psi(y, sd):
        t = y / sd
        return y * 0.5 * np.vectorize(math.erfc)(-t / math.sqrt(2)) + sd * np.exp(-0.5 * t * t) / math.sqrt(2 * math.pi)

    def predicted(r):  # the model's tent, each pair's shot part its expected one given its sum (a linear shrinkage)
        keep = max(1 - (2 * r + 2 / 12) * g * g / total.var(), 0)
        sd = np.sqrt(2 * r + np.maximum(total.mean() + keep * (total - total.mean()), 0))
        safe = np.where(sd > 0, sd, 1.0)
        return np.mean(np.where(sd > 0, 2 * (psi(span, safe) - psi(0, safe)) - span, span))

    low, high = 0.0, 1e4
    if predicted(0.0) <= tent:
        high = 0.0
    for _ in range(60):
        low, high = ((low + high) / 2, high) if predicted((low + high) / 2) > tent else (low, (low + high) / 2)
    return ((low + high) / 2 + 1 / 12) / f


def _frame(pattern, shape, seed, scale=1.0):
    """A textured scene whose bright blob saturates some exposures, censored only in the middle rows; ``scale``
    below 1 darkens the texture (not the blob) to levels a 3x3 window cannot tell from 0."""
    rng = np.random.default_rng(seed)
    h, w = shape
    truth = cv2.GaussianBlur(rng.uniform(2, 60, shape).astype(np.float32), (0, 0), 1.5) * np.float32(scale)
    points = rng.random(shape) < 0.02
    points[:h // 4] = False
    truth[points] *= 8  # isolated bright points: edges for b^2, some saturated
    yy, xx = np.mgrid[:h, :w]
    truth += 900 * np.exp(-((yy - h / 2) ** 2 / (0.01 * h * h) + (xx - w / 3) ** 2 / (0.02 * w * w)))
    return simulate(truth, pattern, SENSOR, seed=seed).raw


@pytest.mark.parametrize("pattern", ["1,4/16,64", "1,2,4/8,16,32/1,4,64", "1/1/8/8"])
@pytest.mark.parametrize("shape", [(37, 41), (300, 50), (130, 200)])  # one strip, strips with and without censored
@pytest.mark.parametrize("scale", [1.0, 0.003])  # bright texture, and texture a 3x3 window cannot tell from 0
def test_kernels_agree_with_the_numpy_formulas(pattern, shape, scale, monkeypatch):
    inp = prepare(_frame(pattern, shape, seed=5, scale=scale), pattern, SENSOR)
    assert 0.005 < inp.censored.mean() < 0.5
    if shape[0] >= 300:
        assert not inp.censored[:60].any()  # whole strips without censored pixels
    image, lower, variance = _reference(inp)
    est = run_method(inp, "adaptive", return_variance=True)
    if scale < 1:  # the wide fallback took part: its scales lowered the variance of many pixels
        with monkeypatch.context() as patch:
            patch.setattr(adaptive, "WIDE_SCALES", 0)
            narrow = adaptive.run(inp, return_variance=True).variance
        assert (est.variance < narrow * 0.5).sum() >= 20
        assert (est.variance < narrow * 0.1).any()  # some through the second scale
    np.testing.assert_array_equal(est.lower_bound, lower)
    # float32 rounding: the kernels order a few operations differently from this statement of the formulas
    np.testing.assert_allclose(est.image, image, rtol=1e-5, atol=1e-5 * float(image.max()))
    np.testing.assert_allclose(est.variance, variance, rtol=1e-5)


@pytest.mark.parametrize("pattern", ["1,4/16,64", "1/1/8/8"])
def test_censored_boxes_at_the_edges_and_inside(pattern):
    """Censored pixels at the corners, along the edges and in small clusters inside: each level's box is cut there."""
    rng = np.random.default_rng(7)
    shape = (150, 90)  # several strips
    truth = cv2.GaussianBlur(rng.uniform(2, 60, shape).astype(np.float32), (0, 0), 1.5)
    clusters = [(slice(0, 3), slice(0, 4)), (slice(-2, None), slice(-3, None)), (slice(70, 72), slice(0, 1)),
                (slice(40, 44), slice(-1, None)), (slice(100, 103), slice(30, 33)), (slice(20, 21), slice(60, 61))]
    for rows, cols in clusters:
        truth[rows, cols] = rng.uniform(100, 3000)  # saturates some exposures
    truth[:3, :4] = truth[-2:, -3:] = truth[100:103, 30:33] = 8000  # all of them: lower bounds
    inp = prepare(simulate(truth, pattern, SENSOR, seed=3).raw, pattern, SENSOR)
    assert 0 < inp.censored.mean() < 0.05
    image, lower, variance = _reference(inp)
    assert lower[:3, :4].any() and lower[-2:, -3:].any() and lower[100:103, 30:33].any()
    est = run_method(inp, "adaptive", return_variance=True)
    np.testing.assert_array_equal(est.lower_bound, lower)
    np.testing.assert_allclose(est.image, image, rtol=1e-5, atol=1e-5 * float(image.max()))
    np.testing.assert_allclose(est.variance, variance, rtol=1e-5)


@pytest.mark.parametrize("box", [(slice(10, 14), slice(20, 23)), (slice(0, 2), slice(0, 3)),
                                 (slice(-3, None), slice(-1, None)), (slice(5, 6), slice(None)),
                                 (slice(None), slice(7, 8))])
def test_bounds_only_in_the_box_of_lower_pixels_equal_whole_frame_ones(box):
    """The lower-bound fill dilates only around the lower pixels (a window radius wider): the frame's values."""
    rng = np.random.default_rng(11)
    raw = np.where(rng.random((30, 40)) < 0.5, 4095, rng.integers(0, 4096, (30, 40))).astype(np.uint16)
    inp = prepare(raw, "1,4/16,64", SENSOR)
    assert inp.censored.mean() > 0.4
    inp.signal[inp.censored] += rng.uniform(0, 50, int(inp.censored.sum())).astype(np.float32)  # bounds differ
    lower = np.zeros(inp.shape, bool)
    lower[box] = rng.random(lower[box].shape) < 0.5
    lower[box][0, 0] = lower[box][-1, -1] = True
    image, variance = rng.random(inp.shape).astype(np.float32), rng.random(inp.shape).astype(np.float32)
    bound = censored_lower_bound(inp, (3, 3))
    expected_image, expected_variance = np.where(lower, bound, image), np.where(lower, bound * bound, variance)
    fill_lower_bounds(inp, lower, (3, 3), image, variance)
    np.testing.assert_array_equal(image, expected_image)
    np.testing.assert_array_equal(variance, expected_variance)


@pytest.mark.parametrize("pattern", ["1/1/8/8", "1,4/16,64"])
@pytest.mark.parametrize("blob", [900.0, 20000.0])  # few censored pixels per row, and rows mostly censored
def test_censored_pixels_equal_the_per_level_window_sums(pattern, blob):
    """Each censored pixel: max(mean of the window's readings consistent with its level's bound, its own), from
    per-level window sums (``smooth``); bit for bit for the 5x3 window (its sums reproduce OpenCV's arithmetic),
    within rounding for the 3x3 one (a pixel's taps added in turn), in rows with few and with many censored
    pixels, up to the frame's edges."""
    rng = np.random.default_rng(3)
    shape = (40, 160)
    truth = cv2.GaussianBlur(rng.uniform(2, 60, shape).astype(np.float32), (0, 0), 1.5)
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    truth += blob * np.exp(-((yy - 20) ** 2 / 150.0 + (xx - 50) ** 2 / 300.0))
    truth[:2, :3] = truth[-3:, -2:] = 8000.0  # corners: every exposure censored
    inp = prepare(simulate(truth, pattern, SENSOR, seed=9).raw, pattern, SENSOR)
    f32, tiny = np.float32, np.float32(parameters.TINY)
    w = np.where(inp.censored, f32(0), rng.uniform(1e-4, 0.05, shape).astype(f32))
    x = inp.signal / inp.exposure
    ky, kx = parameters.kernels(inp.pattern.shape)
    image = np.full(shape, -1, f32)
    lower = censoring.censored_pixels(inp, image, w, x, ky, kx)
    expected, expected_lower = np.full(shape, -1, f32), np.zeros(shape, bool)
    reach = np.where(w > 0, np.sqrt(f32(1) / np.maximum(w, tiny)) * f32(parameters.CONSISTENT_SIGMA) + x, -np.inf)
    for level in inp.pattern.levels:
        at = inp.censored & (inp.exposure == f32(level))
        consistent = (reach >= f32(inp.sensor.censor_level / level)).astype(f32)
        count, total = smooth(consistent, ky, kx), smooth(consistent * x, ky, kx)
        expected = np.where(at, np.maximum(total / np.maximum(count, tiny), x), expected)
        expected_lower |= at & (count <= 0)
    assert expected_lower.any() and (inp.censored & ~expected_lower).any()
    per_row = inp.censored.sum(axis=1)
    assert (per_row * parameters.DENSE_ROW > shape[1]).any()  # rows summed whole
    assert blob > 1000 or ((per_row > 0) & (per_row * parameters.DENSE_ROW <= shape[1])).any()  # and visited
    np.testing.assert_array_equal(lower, expected_lower)
    if len(ky) * len(kx) > censoring.DIRECT_TAPS:
        np.testing.assert_array_equal(image, expected)
    else:
        np.testing.assert_allclose(image, expected, rtol=1e-6)


def zero_at_the_bottom(s: np.ndarray, bottom: np.float32, window: tuple[int, int], image: np.ndarray) -> None:
    """strip_pass._zero_bottom_row on every row of (H, W) arrays, as the fused pass applies it."""
    at_bottom = np.array([strip_pass._count_at_most(row, bottom) for row in s], np.int64)
    low, everywhere = np.empty(s.shape[1], np.bool_), np.empty(s.shape[1], np.bool_)
    for r in range(s.shape[0]):
        strip_pass._zero_bottom_row(s, at_bottom, r, bottom, window[0] // 2, window[1] // 2, low, everywhere, image[r])


@pytest.mark.parametrize("window", [(3, 3), (5, 3), (3, 5), (7, 3)])
@pytest.mark.parametrize("shape", [(40, 57), (7, 1), (6, 2), (9, 3), (1, 9)])
def test_zero_where_the_whole_window_sits_at_the_bottom(window, shape):
    """image = 0 exactly where every reading of the window (borders reflect-101) is at the raw range's bottom."""
    rng = np.random.default_rng(sum(shape) + window[0])
    s = np.where(rng.random(shape) < 0.85, -8.0, rng.uniform(-8, 30, shape)).astype(np.float32)
    bottom = np.float32(-8.0)
    image = rng.uniform(1, 2, shape).astype(np.float32)
    everywhere = cv2.erode((s <= bottom).astype(np.uint8), np.ones(window, np.uint8),
                           borderType=cv2.BORDER_REFLECT_101).astype(bool)
    expected = np.where(everywhere, np.float32(0), image)
    zero_at_the_bottom(s, bottom, window, image)
    np.testing.assert_array_equal(image, expected)
    if shape[0] > 10:
        assert everywhere.any() and not everywhere.all()


@pytest.mark.parametrize("pattern", ["1,2/4,8", "1,4/16,64", "1/1/8/8", "1,4,16/16,1,4/4,16,1"])
def test_wide_fallback_resolves_the_dark_without_the_bright_beside_it(pattern, monkeypatch):
    """A flat region 7 stops below a 4 DN read noise beside a bright one (the grid's small-pixel sensor): far from
    the edge the wide windows' level is much nearer the truth (in stops) than the 3x3 window's answer; next to the
    edge, where a wide window would reach the bright side, the blocks' structure test keeps it out (no pixel
    lifted: the dark side's median does not rise, its error does not grow); the bright side is untouched."""
    sensor = Sensor(12, 64.0, 4095.0, 3000.0 / 4031.0, 4.0)
    truth = np.full((120, 180), 0.02, np.float32)
    truth[:, 90:] = 400.0
    inp = prepare(simulate(truth, pattern, sensor, seed=1).raw, pattern, sensor)
    wide = adaptive.run(inp).image
    with monkeypatch.context() as patch:
        patch.setattr(adaptive, "WIDE_SCALES", 0)
        narrow = adaptive.run(inp).image

    def stops(image, cols):
        return float(np.abs(np.log2(image[:, cols] / truth[:, cols])).mean())

    far, near = slice(10, 60), slice(75, 88)
    assert stops(wide, far) < 0.5 * stops(narrow, far)
    assert np.median(wide[:, near]) <= np.median(narrow[:, near])
    assert stops(wide, near) <= stops(narrow, near)
    np.testing.assert_array_equal(wide[:, 95:], narrow[:, 95:])


def test_wide_fallback_does_not_depend_on_strips_or_threads(monkeypatch):
    """The same result from one strip, from strips, with threads, and with each pixel summing its blocks itself
    (few pixels) or box filters (many): bit for bit."""
    pattern = "1,2/4,8"
    inp = prepare(_frame(pattern, (300, 120), seed=2, scale=0.003), pattern, SENSOR)
    est = adaptive.run(inp, return_variance=True)
    threads = adaptive.run(inp, return_variance=True, workers=3)
    np.testing.assert_array_equal(est.image, threads.image)
    with monkeypatch.context() as patch:
        patch.setattr(adaptive, "_spans", lambda inp, halo, rows: [(0, 0, inp.shape[0], inp.shape[0])])
        whole = adaptive.run(inp, return_variance=True)
    for direct in (0, 10**9):
        with monkeypatch.context() as patch:
            patch.setattr(fallback, "WIDE_DIRECT", direct)
            other = adaptive.run(inp, return_variance=True)
        np.testing.assert_array_equal(est.image, other.image)
        np.testing.assert_array_equal(est.variance, other.variance)
    np.testing.assert_array_equal(est.image, whole.image)
    np.testing.assert_array_equal(est.variance, whole.variance)


@pytest.mark.parametrize("block", [(3, 3), (9, 9), (5, 3), (15, 5), (27, 27)])
def test_blocks_holding_a_censored_reading_are_the_box_filters(block):
    """The wide fallback's blocks that hold a censored reading (a dilation of the mask) are those whose box sum
    of 0/1 flags is positive, borders reflect-101 included, at any density of censored pixels."""
    by, bx = block
    rng = np.random.default_rng(by * 100 + bx)
    for density in (0.0005, 0.01, 0.2):
        censored = rng.random((3 * by + 17, 3 * bx + 11)) < density
        censored[0, -1] = True  # a corner: blocks reflected across both edges hold it
        flags = cv2.boxFilter(censored.astype(np.float32), cv2.CV_32F, (bx, by), normalize=False,
                              borderType=cv2.BORDER_REFLECT_101)
        np.testing.assert_array_equal(fallback._held(censored, by, bx), flags > 0.5)


@pytest.mark.parametrize("shape, offset, block", [((290, 1920), 30, (3, 3)), ((40, 13), 5, (5, 3)),
                                                  ((12, 7), 2, (3, 3)), ((50, 4), 10, (3, 1)), ((9, 5), 0, (3, 3))])
def test_unheld_leaves_out_the_pixels_whose_blocks_hold_a_censored_reading(shape, offset, block):
    """fallback._unheld clears exactly the active pixels one of whose eight blocks (one block away, reflect-101)
    holds a censored reading, the pixels the wide fallback's first scale leaves unchanged (its bad blocks)."""
    by, bx = block
    rng = np.random.default_rng(shape[0] * 7 + shape[1])
    held = rng.random(shape) < 0.05
    active = rng.random((min(20, shape[0] - offset), shape[1])) < 0.5
    expected = active.copy()
    for r, c in zip(*np.nonzero(active)):
        expected[r, c] = not any(held[reflect_101(r + offset + i * by, shape[0]), reflect_101(c + j * bx, shape[1])]
                                 for i in (-1, 0, 1) for j in (-1, 0, 1) if (i, j) != (0, 0))
    got = active.copy()
    assert fallback._unheld(held, offset, by, bx, got) == np.count_nonzero(expected)
    np.testing.assert_array_equal(got, expected)

@pytest.mark.parametrize("block", [(3, 3), (5, 3), (9, 9)])
def test_a_pixels_censored_blocks_found_in_the_readings_or_the_dilation(block):
    """The direct wide step's test of a pixel's eight blocks for a censored reading, in the readings
    (fallback._censored_near) and in the dilation (fallback._held_near of fallback._held), is the blocks' own
    (reflect-101 at every edge)."""
    by, bx = block
    rng = np.random.default_rng(by * 10 + bx)
    shape = (3 * by + 7, 3 * bx + 5)
    censored = rng.random(shape) < 0.01
    held = fallback._held(censored, by, bx)
    for r in range(shape[0]):
        for c in range(shape[1]):
            expected = any(censored[reflect_101(r + i * by + dy, shape[0]), reflect_101(c + j * bx + dx, shape[1])]
                           for i in (-1, 0, 1) for j in (-1, 0, 1) if (i, j) != (0, 0)
                           for dy in range(-(by // 2), by // 2 + 1) for dx in range(-(bx // 2), bx // 2 + 1))
            assert fallback._censored_near(censored, r, c, by, bx) == expected
            assert fallback._held_near(held, r, c, by, bx) == expected


@pytest.mark.parametrize("ky, kx, blocks", [(3, 3, 1), (5, 3, 1), (3, 3, 3), (5, 3, 3)])
def test_wide_direct_is_its_blocks_sums_written_out(ky, kx, blocks):
    """fallback._wide_direct (three windows' sums at a time) gives at every active pixel the estimate, information
    and flags of its eight blocks summed window by window, each window's readings in float64 row by row, the
    windows three by three in float32 (fallback._threefold_block), borders reflect-101 included; weights over
    twelve decades, readings at four exposures; the same with the weights' rows read through an index (the
    strips' rows of one array, fallback.WeightRows)."""
    rng = np.random.default_rng(ky * 10 + blocks)
    shape = (3 * ky * blocks + 9, 3 * kx * blocks + 14)
    weights = (10.0 ** rng.uniform(-6, 6, shape)).astype(np.float32)
    signal = rng.uniform(0, 4000, shape).astype(np.float32)
    exposure = rng.choice(np.array([1, 2, 4, 8], np.float32), shape)
    offset, none = 2, np.empty((0, 0), bool)
    active = rng.random((shape[0] - 4, shape[1])) < 0.3
    estimate = rng.normal(0, 1, active.shape).astype(np.float32)
    information = rng.uniform(0.1, 2, active.shape).astype(np.float32)
    got = [a.copy() for a in (active, np.zeros_like(active), estimate, information)]
    kept = fallback._wide_direct(weights, np.arange(shape[0]), signal, exposure, none, none, offset, ky, kx, blocks,
                                 *got)
    # the weights' rows read through an index from a larger array of them in another order: the same results
    order = rng.permutation(shape[0] + 5)[:shape[0]]
    pool = np.full((shape[0] + 5, shape[1]), np.nan, np.float32)
    pool[order] = weights
    through = [a.copy() for a in (active, np.zeros_like(active), estimate, information)]
    assert fallback._wide_direct(pool, order, signal, exposure, none, none, offset, ky, kx, blocks, *through) == kept
    for g, t in zip(got, through):
        np.testing.assert_array_equal(g, t)
    expected = [a.copy() for a in (active, np.zeros_like(active), estimate, information)]
    by, bx, tiny = ky * blocks, kx * blocks, np.float32(parameters.TINY)
    block_w, block_m = np.empty(8, np.float32), np.empty(8, np.float32)
    expected_kept = 0
    for r, c in zip(*np.nonzero(active)):
        for i in [i for i in range(9) if i != 4]:
            sums = np.empty((2, blocks, blocks), np.float32)
            for a in range(blocks):
                top = r + offset + (i // 3 - 1) * by + (a - blocks // 2) * ky - ky // 2
                for b in range(blocks):
                    left = c + (i % 3 - 1) * bx + (b - blocks // 2) * kx - kx // 2
                    sum_w, sum_x = 0.0, 0.0
                    for dy in range(ky):
                        for dx in range(kx):
                            q = reflect_101(top + dy, shape[0]), reflect_101(left + dx, shape[1])
                            sum_w += float(weights[q])
                            sum_x += float(weights[q] * (signal[q] / exposure[q]))
                    sums[:, a, b] = sum_w, sum_x
            fallback._threefold_block(sums[0])
            fallback._threefold_block(sums[1])
            w, x = sums[0, 0, 0], sums[1, 0, 0]
            block_w[i - (i > 4)], block_m[i - (i > 4)] = w, (x / max(w, tiny) if w > tiny else np.float32(0.0))
        expected_kept += fallback._wide_blend(block_w, block_m, r, c, *expected)
    assert kept == expected_kept
    for g, e in zip(got, expected):
        np.testing.assert_array_equal(g, e)


def test_true_positions_are_numpys_at_any_density():
    """base.true_positions (words of eight flags skipped where a row has few, else one position a flag) gives
    np.flatnonzero, on rows of any length (not whole words too) and rows of a 2-D array."""
    rng = np.random.default_rng(11)
    for size in (1, 7, 8, 9, 64, 1920, 1923):
        for share in (0.0, 0.01, 0.06, 0.3, 1.0):
            flags = np.zeros((3, size), bool)
            flags[1] = rng.random(size) < share
            index = np.full(size, -1, np.int64)
            n = true_positions(flags[1], int(flags[1].sum()), index)
            np.testing.assert_array_equal(index[:n], np.flatnonzero(flags[1]))

@pytest.mark.parametrize("block, shape", [
    (block, shape) for block in [(3, 3), (5, 3), (3, 1), (1, 3), (9, 9)]
    for shape in [(290, 1920), (27, 27), (30, 9), (100, 45), (45, 31)]
    if 3 * block[0] <= shape[0] and 3 * block[1] <= shape[1]])  # (blocks three times larger fit the array)
def test_threefold_box_sums_are_the_box_filters_three_times_larger(block, shape):
    """The wide fallback's next scale's block sums, made from the last scale's (3 x 3 of them around each pixel),
    are OpenCV's box filter three times as large, borders reflect-101 included, within float32 rounding (OpenCV
    sums in float64); sparse weights with empty blocks give exact zeros."""
    by, bx = block
    rng = np.random.default_rng(shape[0] + by)
    for values in (rng.uniform(0, 10, shape), rng.uniform(-5, 10, shape) * (rng.random(shape) < 0.05)):
        values = values.astype(np.float32)
        expected = fallback._box(values, 3 * by, 3 * bx)
        got = fallback._box(values, by, bx)
        fallback._threefold(got, by, bx, np.empty_like(got))
        np.testing.assert_allclose(got, expected, rtol=1e-6, atol=1e-6 * float(np.abs(expected).max()))
        np.testing.assert_array_equal(got == 0, expected == 0)

def _passes(inp, noise):
    """Steps 1-4 of adaptive._solve as separate passes over whole arrays, OpenCV's window sums between the
    kernels (the method before they were fused into one pass): dict of (H, W) arrays."""
    f32 = np.float32
    ky, kx = parameters.kernels(inp.pattern.shape)
    window = (len(ky), len(kx))
    gain_inv, floor = f32(noise[0]), f32(noise[1])
    centre = f32(ky[len(ky) // 2] * kx[len(kx) // 2])
    kernel_square = f32((ky * ky).sum() * (kx * kx).sum())
    s, e, censored = inp.signal, inp.exposure, inp.censored
    w, x, wn, wx = (np.empty(inp.shape, f32) for _ in range(4))
    exposure_sum = smooth(np.where(censored, f32(0), e), ky, kx)
    lowest = cv2.erode(np.where(censored, e, f32(parameters.BIG)), np.ones(window, np.uint8),
                       borderType=cv2.BORDER_REFLECT_101)
    signal_sum, *arrays = flat(smooth(np.where(censored, f32(0), s), ky, kx), exposure_sum, s, e, censored, lowest, w,
                               x, wn, wx)
    strip_pass._weights_censored(strip_pass._summed(signal_sum), *arrays, gain_inv, floor, centre)
    var_m, m = smooth(wn, ky, kx), smooth(wx, ky, kx)
    excess_q, q, var_r = wx, np.empty(inp.shape, f32), np.empty(inp.shape, f32)
    # the sums as made sums (strip_pass._summed), read and then overwritten pixel by pixel
    var_m_flat, m_flat, *arrays = flat(var_m, m, wn, w, x, excess_q, q, var_r)
    strip_pass._residuals(strip_pass._summed(var_m_flat), strip_pass._summed(m_flat), var_m_flat, m_flat, *arrays,
                          centre, kernel_square)
    image, total = smooth(excess_q, ky, kx), smooth(q, ky, kx)
    image_flat, total_flat, *arrays = flat(image, total, var_m, m, var_r, w, x, e)
    strip_pass._blend(strip_pass._summed(image_flat), strip_pass._summed(total_flat), image_flat, total_flat, *arrays,
                      gain_inv, floor,
                      f32(parameters.CONTRAST_SIGMA**2 * 2.0) * kernel_square,
                      posterior.posterior_polynomial(), np.empty(image.size, bool), np.empty(image.size, bool))
    zero_at_the_bottom(s, -f32(inp.sensor.black_level), window, image)
    lower = exposure_sum <= 0
    if censored.any():
        lower |= censoring.censored_pixels(inp, image, w, x, ky, kx)
    variance = f32(1) / total
    fill_lower_bounds(inp, lower, window, image, variance)
    candidates = np.empty(inp.shape, bool)
    strip_pass._candidates(*flat(var_m, total, image, censored, lower, candidates), f32(parameters.CONTRAST_SIGMA**2))
    return dict(image=image, lower=lower, variance=variance, w=w, wn=wn, estimate=var_m, information=total,
                candidates=candidates)


def _inputs(pattern, shape, seed):
    """Random readings (dark and bright, some at raw 0 under a black level), a simulated frame with censored
    pixels (_frame), and each with its exposures scaled per pixel as a folded colour input's are."""
    rng = np.random.default_rng(seed)
    sensor = Sensor(12, black_level=64, gain=0.4, read_noise=2.0)
    raw = rng.uniform(0, 4095, shape) * (rng.random(shape) < 0.7) ** 2 * rng.uniform(0.001, 1, shape[1])
    raw = np.where(rng.random(shape) < 0.1, 0, raw).astype(np.uint16)
    raw[: shape[0] // 3, : shape[1] // 2] = 0  # a corner at raw 0: the whole window at the bottom
    inputs = [prepare(raw, pattern, sensor), prepare(_frame(pattern, shape, seed), pattern, SENSOR)]
    for inp in inputs[:2]:
        share = rng.uniform(0.2, 1.5, shape).astype(np.float32)
        inputs.append(dataclasses.replace(inp, exposure=inp.exposure * share, folded=True))
    return inputs


@pytest.mark.parametrize("window", strip_pass.SHARED_SUMS)
@pytest.mark.parametrize("shape", [(40, 67), (5, 1920), (2, 3), (1, 1)])
def test_shared_sums_are_the_pass_filters_bit_for_bit(window, shape):
    """On the windows of SHARED_SUMS, OpenCV's sums (base.smooth, which makes the pattern's cached exposure sums)
    equal the pass's own row and column filters bit for bit on any float32 values, at the borders too."""
    ky, kx = binomial_kernel(window[0]), binomial_kernel(window[1])
    values = np.random.default_rng(shape[1]).uniform(0.01, 300, shape).astype(np.float32)
    rows = np.empty_like(values)
    for r in range(shape[0]):
        strip_pass._row_filter(values[r], kx, rows[r])
    got, taps = np.empty_like(values), np.empty(ky.size, np.int64)
    for r in range(shape[0]):
        strip_pass._window_rows(r, shape[0], shape[0], taps)
        strip_pass._column_filter(rows, taps, ky, got[r])
    np.testing.assert_array_equal(got, smooth(values, ky, kx))


@pytest.mark.parametrize("pattern", ["1,4/16,64", "1/1/8/8", "1,2,4,8/16,32,64,1", "1/2/4/8/16/32"])
@pytest.mark.parametrize("shape", [(300, 67), (130, 1), (7, 33), (3, 5), (2, 2), (13, 4)])
def test_fused_pass_equals_the_separate_passes(pattern, shape):
    """adaptive._solve's one compiled pass (strip_pass.fused_pass: row and column filters into rings of rows) against the
    chain of OpenCV window sums and kernels it replaced, strip by strip as the method cuts the frame (the rows
    kept, the halo's reflected borders at the strip's ends), odd and tiny widths and heights: bit for bit where
    OpenCV's sums are computed in the same order (3-tap rows, 3- or 5-tap columns), else within float32 rounding."""
    ky, kx = parameters.kernels(Pattern.parse(pattern).shape)
    exact = (len(ky), len(kx)) in strip_pass.SHARED_SUMS
    z2 = np.float32(parameters.CONTRAST_SIGMA**2)
    checked = {"strips": 0, "censored": 0, "bottom": 0, "candidates": 0}
    for inp in _inputs(pattern, shape, seed=shape[0] + 7 * shape[1]):
        noise = evidence.noise_model(inp)
        frame = adaptive._frame_settings(inp, noise, ky, kx)
        for start, top, bottom, stop in adaptive._spans(inp, 3 * (max(len(ky), len(kx)) // 2), 64):
            crop = inp.crop(slice(start, stop))
            keep = slice(top - start, bottom - start)
            expected = {name: a[keep] for name, a in _passes(crop, noise).items()}
            image, lower, variance, own, dark = adaptive._solve(crop, frame, True, True, keep)
            got = dict(image=image, lower=lower, variance=variance, w=own, wn=dark.weights, estimate=dark.estimate,
                       information=dark.information, candidates=dark.candidates)
            got = {name: a[keep] for name, a in got.items()}
            assert dark.count == np.count_nonzero(got["candidates"])
            checked["strips"] += 1
            checked["censored"] += bool(crop.censored[keep].any())
            checked["bottom"] += bool((expected["image"] == 0).any())
            checked["candidates"] += bool(expected["candidates"].any())
            np.testing.assert_array_equal(got["lower"], expected["lower"])
            if exact:
                for name in expected:
                    np.testing.assert_array_equal(got[name], expected[name], err_msg=name)
                continue
            # sums rounded in another order: the weights within a few ulps; the quantities after the squared-bias
            # step more where its estimate B nearly cancels its shrinkage 2 SE (a difference of near-equal sums)
            for name, rtol in (("w", 4e-6), ("wn", 4e-6), ("estimate", 1e-4), ("image", 1e-4),
                               ("information", 1e-3), ("variance", 1e-3)):
                a, b = expected[name], got[name]
                np.testing.assert_allclose(b, a, rtol=rtol, atol=rtol * float(np.abs(a).max()), err_msg=name)
            # a candidate may flip only where its test sits within rounding of the threshold
            estimate, information = expected["estimate"], expected["information"]
            near = np.abs(estimate * estimate * information - z2) <= 1e-4 * z2
            assert not (got["candidates"] != expected["candidates"])[~near].any()
    if shape[0] > 64 and shape[1] > 1:  # strips of a frame, holding each kind of pixel
        assert checked["strips"] >= 8 and checked["censored"] and checked["bottom"] and checked["candidates"]


def test_path_shares_follow_the_frame():
    """benchmarks/paths.py's shares: a flat bright frame with a saturated block takes the censored step there and
    hardly anything near 0 (only beside the block, whose dark side loses its neighbours); the same scene 9 stops
    darker (without the block) takes step 4 and the wide fallback, with nothing censored; the plain share is the
    rest."""
    pattern = "1,4/16,64"
    truth = np.full((96, 128), 30.0, np.float32)
    truth[40:60, 40:80] = 1e5  # clipped in every exposure
    bright = adaptive.path_shares(prepare(simulate(truth, pattern, SENSOR, seed=3).raw, pattern, SENSOR))
    dark = np.full(truth.shape, 30.0 / 512, np.float32)
    dim = adaptive.path_shares(prepare(simulate(dark, pattern, SENSOR, seed=3).raw, pattern, SENSOR))
    assert bright["censored"] >= 20 * 40 / truth.size and bright["censored_rows"] >= 20 / 96
    assert bright["near_zero"] < 0.01 and bright["wide"] == 0 and bright["wide_strips"] == 0
    assert dim["censored"] == 0 and dim["near_zero"] > 0.5 and dim["wide"] > 0 and dim["wide_strips"] > 0
    for shares in (bright, dim):
        assert 0 <= shares["plain"] <= 1 - max(shares["censored"], shares["near_zero"], shares["wide"])


@pytest.mark.parametrize("pattern", ["1,4/16,64", "1,2/4,8", "1,8/8,1"])
@pytest.mark.parametrize("clipped", [False, True])  # with a block clipped in every exposure (windows with no reading)
def test_the_window_mean_made_in_the_pass_is_the_motion_tests_own(pattern, clipped):
    """adaptive.run(window=True) gives numerics.window_estimate's window mean and variance bit for bit (completed
    where the window holds no uncensored reading), from one strip or many, on one thread or three."""
    from svelive.reconstruction.numerics import completed_window, window_estimate

    raw = _frame(pattern, (200, 150), seed=4, scale=0.01)
    if clipped:
        raw[120:150, 30:70] = SENSOR.white_level
    inp = prepare(raw, pattern, SENSOR)
    for workers in (1, 3):
        est = adaptive.run(inp, return_variance=True, workers=workers, window=True)
        assert est.window is not None
        if clipped:
            assert np.isinf(est.window[1]).any()  # the case the completion is for
        level, variance = completed_window(est.window, est.image, est.variance)
        reference = window_estimate(inp, est.image, est.variance)
        np.testing.assert_array_equal(level, reference[0])
        np.testing.assert_array_equal(variance, reference[1])


def test_no_window_where_the_methods_window_is_not_the_motion_tests():
    """Line-interleaved exposures: the method's window is 5x3, the motion tests' 5x1: none is made."""
    inp = prepare(_frame("1/1/8/8", (80, 60), seed=1, scale=1.0), "1/1/8/8", SENSOR)
    assert adaptive.run(inp, window=True).window is None
    assert adaptive.run(inp).window is None


def test_a_stream_is_the_same_with_the_window_from_the_pass(monkeypatch):
    """svelive.Reconstructor takes the window mean from the method's pass where it can: every fused frame and
    motion mask is what the separate window pass gives."""
    from svelive.reconstruction import Reconstructor
    from svelive.reconstruction.methods import METHODS
    from svelive.scenes import moving_disc, render_sequence

    pattern = "1,4/16,64"
    rng = np.random.default_rng(2)
    scene = cv2.GaussianBlur(rng.uniform(2, 60, (120, 160)).astype(np.float32), (0, 0), 1.5)  # a textured background
    raws = [f.raw for f in render_sequence(moving_disc(scene, 3000.0, 10.0, (30.0, 30.0), (4.0, 3.0)), 5, pattern,
                                           SENSOR, seed=5)]
    runs = []
    for window in (True, False):
        monkeypatch.setitem(METHODS, "adaptive", dataclasses.replace(METHODS["adaptive"], window=window))
        with Reconstructor(pattern, white_level=4095, gain=SENSOR.gain, read_noise=SENSOR.read_noise) as stream:
            runs.append([stream.process(raw) for raw in raws])
    assert any(r.motion.any() for r in runs[0])
    for with_pass, without in zip(*runs):
        np.testing.assert_array_equal(with_pass.image, without.image)
        np.testing.assert_array_equal(with_pass.motion, without.motion)


@pytest.mark.parametrize("top", range(4))
def test_a_small_bright_light_keeps_its_level_at_every_row_phase(top):
    """A 3x3 light on a dark field, at each row of a 1/1/8/8 tile: its edge rows read their level, not about half
    of it (the window's bias estimate, weighted by precision, was outvoted by the dark side's readings; the
    pixel's own residual now counts, strip_pass.OWN_SIGMA)."""
    sensor = Sensor.from_full_well(12, 10_000, 3)
    scene = np.full((24, 24), 2.0, np.float32)
    scene[8 + top:11 + top, 10:13] = 300.0  # the long rows read 2400 DN: nothing is censored
    raw = simulate(scene, "1/1/8/8", sensor, seed=1)
    hdr = adaptive.run(prepare(getattr(raw, "raw", raw), "1/1/8/8", sensor)).image
    light = hdr[8 + top:11 + top, 10:13]
    # a short reading of 300 DN has a deviation of about 11 DN (4 %): 15 % is four of them
    assert np.abs(light / 300.0 - 1).max() < 0.15, light


def test_strips_without_dark_pixels_free_what_only_the_wide_fallback_reads():
    """A frame dark at the top and bright below: the bright strips' Dark keeps only the weights (the fallback's
    blocks reach into them), the dark strips' keep all; the result is the same as when every strip keeps all."""
    pattern = "1,4/16,64"
    truth = np.full((384, 128), 300.0, np.float32)
    truth[:96] = 300.0 / 2**9  # cannot tell its level from 0 in a 3x3 window
    inp = prepare(simulate(truth, pattern, SENSOR, seed=5).raw, pattern, SENSOR)
    noise = evidence.noise_model(inp)
    lean = adaptive._estimate(inp, noise, 1, want_variance=True)
    full = adaptive._estimate(inp, noise, 1, want_variance=True, want_darks=True)
    darks = lean[4]
    assert len(darks) >= 4 and darks[0].count > 0 and darks[-1].count == 0
    for dark, whole in zip(darks, full[4]):
        assert dark.weights.shape == whole.weights.shape
        kept = dark.count > 0
        assert (dark.estimate.size > 0) == kept and (dark.candidates.size > 0) == kept
    for a, b in zip(lean[:3], full[:3]):
        np.testing.assert_array_equal(a, b)
