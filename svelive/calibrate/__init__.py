"""Calibration from data: the camera's response, the exposure mask, the noise model."""

from svelive.calibrate.mask import MaskConfig, MaskEstimate, estimate_mask, load_mask, save_mask
from svelive.calibrate.noise import NoiseModel, calibrate_noise
from svelive.calibrate.response import (
                                        CURVES,
                                        ResponseFitConfig,
                                        calibrate_frame,
                                        fit_response,
                                        load_response,
                                        save_response,
                                        simulate_nonlinear,
)
from svelive.core.response import Response, linearise

__all__ = ["CURVES", "MaskConfig", "MaskEstimate", "NoiseModel", "Response", "ResponseFitConfig",
           "calibrate_frame", "calibrate_noise", "estimate_mask", "fit_response", "linearise", "load_mask",
           "load_response", "save_mask", "save_response", "simulate_nonlinear"]
