"""svelive.core.order: numpy's percentile and median by one partition."""

import numpy as np
import pytest

from svelive.core import order
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


@pytest.mark.parametrize("case", ["float32", "nans", "top ties", "top in the sample"])
@pytest.mark.parametrize("q", [95.0, 99.0, 99.5, 99.99, 100.0])
def test_a_high_quantile_of_a_long_array_from_its_top_values_is_the_whole_partitions(case, q, monkeypatch):
    """A rank in the top few per cent of a long array is found among the values above a bound from every 16th
    (order._upper_part): numpy's value in float64, and in float32 the one partition of the whole array's; NaNs
    sort last, and where the bound leaves too few the whole array is partitioned."""
    values = _values(144_000, np.float32)
    if case == "nans":
        values[::997] = np.nan
    elif case == "top ties":
        values[-5000:] = values.max()
    elif case == "top in the sample":  # every 16th value is above the others: its bound leaves too few
        values[::16] += 1
    wide = values.astype(np.float64)
    tail = percentile(values, q), percentile(wide, q)
    np.testing.assert_array_equal(tail[1], np.percentile(wide, q))
    monkeypatch.setattr(order, "TAIL_SIZE", values.size + 1)  # the whole array's partition
    np.testing.assert_array_equal(tail, (percentile(values, q), percentile(wide, q)))


@pytest.mark.parametrize("n", [1, 2, 1000, 27_000, 144_000])
@pytest.mark.parametrize("share", [0.0, 0.25, 0.5, 0.96, 0.999, 1.0])
def test_order_statistic_is_numpys_partition_value(n, share):
    """The k-th smallest, from the top values only for a rank in the top few per cent of a long array (the white
    balance's upper luminance bound): np.partition's value and dtype."""
    values = _values(n, np.float32)
    k = int(share * (n - 1))
    ours, theirs = order.order_statistic(values, k), np.partition(values, k)[k]
    assert ours.dtype == theirs.dtype and ours == theirs
    assert values.tobytes() == _values(n, np.float32).tobytes()
