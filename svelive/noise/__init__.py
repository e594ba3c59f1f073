"""The noise model from the data: gain (electrons per DN) and read noise (DN) of a sensor, from its frames.

The model is the sensor's (svelive/core/sensor.py): a reading with expected signal
``s`` DN above black has variance ``s / gain + read_noise^2 + 1/12`` DN^2 (the
1/12 is uniform quantisation). One module per job (docs/noise.md tells the method):

- ``model.py``: the value types (:class:`EstimatorConfig`, :class:`NoiseEstimate`, :class:`NoiseSamples`,
  :class:`LineFit`) and what reads estimates (:func:`variance_uncertainty`, :func:`agree`);
- ``stats.py``: robust statistics, signal bins and the weighted line fit (:func:`bin_samples`,
  :func:`fit_line`), chi-square quantiles (:func:`chi2_quantile`);
- ``prior.py``: the prior every estimate is combined with, and a fitted line as an estimate
  (:func:`estimate_from_fit`);
- ``inputs.py``: what the estimators read of a camera and a frame;
- ``frame.py``: one frame's estimate (:func:`estimate_from_frame`, :func:`frame_fit`), from residuals
  against more exposed neighbours at flat places (:func:`frame_samples`);
- ``cancellation.py``: one frame's line with texture cancelled across exposures (:func:`cancellation_fit`,
  :func:`joint_texture_fit`);
- ``temporal.py``: samples from static pixels of consecutive frames (:func:`temporal_samples`,
  :func:`triple_samples`, :func:`pair_fit`);
- ``tracker.py``: the model of one stream refined frame by frame (:class:`NoiseTracker`);
- ``stream.py``: when a stream refines its model and trusts it (:class:`NoiseSchedule`, :class:`StreamNoise`).

The modules import each other directly; this package re-exports their public names. Nothing here imports
svelive.calibrate (which builds its noise calibration on these).
"""

from svelive.noise.cancellation import cancellation_fit, joint_texture_fit
from svelive.noise.frame import estimate_from_frame, frame_fit, frame_samples
from svelive.noise.model import (
    QUANTISATION_VARIANCE,
    EstimatorConfig,
    LineFit,
    NoiseEstimate,
    NoiseSamples,
    agree,
    variance_uncertainty,
)
from svelive.noise.prior import PRIOR_LOG_SIGMA, estimate_from_fit
from svelive.noise.stats import bin_samples, chi2_quantile, chi2_quantile_array, fit_line
from svelive.noise.stream import NoiseSchedule, StreamNoise
from svelive.noise.temporal import pair_fit, temporal_samples, triple_samples
from svelive.noise.tracker import NoiseTracker

__all__ = ["PRIOR_LOG_SIGMA", "QUANTISATION_VARIANCE", "EstimatorConfig", "LineFit", "NoiseEstimate", "NoiseSamples",
           "NoiseSchedule", "NoiseTracker", "StreamNoise", "agree", "bin_samples", "cancellation_fit", "chi2_quantile",
           "chi2_quantile_array", "estimate_from_fit", "estimate_from_frame", "fit_line", "frame_fit", "frame_samples",
           "joint_texture_fit", "pair_fit", "temporal_samples", "triple_samples", "variance_uncertainty"]
