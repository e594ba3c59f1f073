"""The camera's response function from one SVE frame (paper section 8; Mitsunaga and Nayar 1999).

Brightness ``M`` (raw minus black, divided by white minus black: 0..1) relates to
scaled linear radiance ``I`` by the inverse response ``I = f(M) = sum c_n M^n``,
normalised by ``f(1) = 1``. Neighbouring pixels of an SVE frame see the scene
with known exposure ratios, so where the scene is locally constant the means of
the exposure sub-images over a small window obey ``f(M_l) = R_lk f(M_k)``,
``R_lk = e_l / e_k``: a linear least-squares problem in the ``c_n``.

Steps (:func:`fit_response`):

1. Per exposure level, mean and variance of its readings over windows of
   ``window`` x ``window`` tiles; windows with a clipped reading are dropped.
2. The noise variance at each brightness is measured from the frame itself
   (:func:`svelive.calibrate.noise.noise_curve_frame`); a window is "locally
   constant" when its variance is what noise alone would give at the
   ``flat_quantile`` level of a chi-square test.
3. Every pair of flat levels at a location gives ``f(M_hi) / R - f(M_lo) = 0``,
   normalised by the window values' noise (including the rounding bias a
   constant window shares) propagated through ``f'`` of the previous pass.
   The curve's shape is solved scale-free in a Legendre basis on [0, 1] (the
   smallest generalised eigenvector of the normalised residuals against the
   equations' scale), then scaled to ``f(1) = 1``: imposing ``f(1) = 1`` inside
   the least squares drifts where ``M = 1`` has no data.
4. The degree is the lowest one whose error on held-out locations (spatial
   folds, so held-out windows do not share pixels with training ones) is within
   one standard error of the best degree's (the one-standard-error rule), among
   degrees whose curve is monotone on the measured range.
5. The measured range is the longest brightness interval with data in every
   1/16 of full scale and a standard error of ``f`` (from the fit's covariance)
   under 1 %: gaps in the data end it.
6. For sweeps without a common exposure ratio (``max_knots``, on by default) a log-spline
   competes with the polynomials: ``log f`` a natural cubic spline in ``log M`` with
   ``max_knots`` knots evenly spaced in logit(M) over the data (a power law above the top
   of the data, up to white), fitted by least squares on ``log f(M_hi) - log f(M_lo) =
   log R`` (:func:`_solve_spline`), and a power law (2 knots); the same held-out rule
   chooses among them and the degrees, on the equations whose darker value rounding cannot
   move by more than 1 % (:func:`_undithered` has why). The splines also maximise the likelihood
   of which pixels reach white in a brighter frame given their reading in a darker one (a probit,
   :func:`_censored_with_pilot`): that pins the curve at white, hence its scale, with no window
   selected on its pixels' texture. On by default for sweeps (:data:`SWEEP_KNOTS`; see the docs).
7. Optionally (``refine_ratios``) the exposure ratios are re-estimated from the
   fitted curve and the fit repeated; the ratio of the extreme exposures is kept
   at its nominal value because ``f^g`` with ratios ``R^g`` fits the same data
   for any ``g`` (the exponential ambiguity of ratio-based calibration).
docs/calibration.md has the details and the measured accuracy.

The modules, one job each: ``config`` (the options), ``pairs`` (window statistics, flat windows, the ratio
equations), ``polynomial`` and ``spline`` (the two models, with their standard errors), ``censored`` (a
sweep's pixels at white and the probit likelihood), ``selection`` (monotonicity, held-out errors, the
jackknife band and the measured range), ``fit`` (:func:`fit_response`, :func:`calibrate_frame`), ``files``
(JSON on disk) and ``nonlinear`` (known curves, simulated non-linear cameras). The value type
:class:`~svelive.core.response.Response` and ``linearise`` are the ground floor's (svelive.core.response).
"""

from svelive.calibrate.response.config import SWEEP_KNOTS, ResponseFitConfig
from svelive.calibrate.response.files import load_response, save_response, write_json
from svelive.calibrate.response.fit import calibrate_frame, common_ratio, fit_response
from svelive.calibrate.response.nonlinear import CURVES, POLY3, ResponseCurve, simulate_nonlinear
from svelive.calibrate.response.pairs import _collect_pairs, level_window_statistics, quantisation_bias_variance
from svelive.calibrate.response.polynomial import _solve
from svelive.calibrate.response.spline import spline_knots
from svelive.core.response import Response, log_spline_basis

__all__ = ["CURVES", "POLY3", "SWEEP_KNOTS", "Response", "ResponseCurve", "ResponseFitConfig", "calibrate_frame",
           "common_ratio", "fit_response", "level_window_statistics", "load_response",
           "log_spline_basis", "quantisation_bias_variance", "save_response", "simulate_nonlinear", "spline_knots",
           "write_json",
           # two steps benchmarks/calibrate_response.py times on their own
           "_collect_pairs", "_solve"]
