"""The live pipeline (moving into one module per stage)."""

from service.pipeline.pipeline import (CalibrationBusy, EncodedFrame, FrameReconstructor, LatencyWindow, NewestSlot,
                                       Pipeline, PipelineConfig, Published, RateMeter, no_signal_image,
                                       opencv_threads)

__all__ = ["CalibrationBusy", "EncodedFrame", "FrameReconstructor", "LatencyWindow", "NewestSlot", "Pipeline",
           "PipelineConfig", "Published", "RateMeter", "no_signal_image", "opencv_threads"]
