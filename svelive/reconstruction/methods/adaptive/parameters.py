"""The ``adaptive`` method's fixed significance levels, numeric floors and window kernels (shared by its steps)."""

from __future__ import annotations

import numpy as np

from svelive.reconstruction.methods.base import binomial_kernel, support_size


#: Significance, in standard deviations of a reading, of "consistent with a censored bound".
CONSISTENT_SIGMA = 2.0
#: Significance, in standard errors of the window's squared-bias estimate, of structure (texture, an edge):
#: the estimate is shrunk by this many standard errors, so where the window cannot tell structure from noise the
#: result is the neighbourhood's noise-optimal mean.
CONTRAST_SIGMA = 2.0
TINY = 1e-12  # floor of sums of inverse variances (real ones exceed 1e-7)
BIG = 1e30  # exposure given to censored pixels when looking for uncensored ones


def kernels(pattern_shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Binomial (rows, cols) kernels, float32: the tile's support, at least 3 taps so every pixel has neighbours."""
    th, tw = pattern_shape
    return binomial_kernel(max(support_size(th), 3)), binomial_kernel(max(support_size(tw), 3))


#: A row of :func:`_censored_each` or :func:`_censored_separable` with more than one censored pixel in this many
#: sums every pixel's window at once (measured on the benchmark's frames: 32 beat 8 and 96).
DENSE_ROW = 32
