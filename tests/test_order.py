"""svelive.core.order: numpy's percentile and median by one partition."""

import numpy as np
import pytest

from svelive.core.order import median, percentile, quantile


def _values(n: int, dtype) -> np.ndarray:
    values = np.random.default_rng(n).lognormal(0.0, 0.05, n).astype(dtype)
    values[:n // 3] = values[0]  # ties
    return values


@pytest.mark.parametrize("n", [1, 2, 7, 1000, 36_001, 144_000])
@pytest.mark.parametrize("q", [0.0, 50.0, 99.5, 100.0])
def test_percentile_and_quantile_are_numpys_bit_for_bit(n, q):
    values = np.log2(_values(n, np.float32)).astype(np.float64)
    assert percentile(values, q) == float(np.percentile(values, q))
    assert quantile(values, q / 100) == float(np.quantile(values, q / 100))


@pytest.mark.parametrize("n", [1, 2, 3, 1000, 1001, 36_000, 36_001])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_median_is_numpys_bit_for_bit(n, dtype):
    values = _values(n, dtype)
    ours, theirs = median(values), np.median(values)
    assert ours.dtype == theirs.dtype and ours.tobytes() == theirs.tobytes()
    assert values.tobytes() == _values(n, dtype).tobytes()  # the input is left as it was
