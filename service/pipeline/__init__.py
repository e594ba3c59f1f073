"""The live pipeline: capture thread -> newest-frame hand-off -> reconstruction -> preview encoder.

    capture thread ──(Frame)──> NewestSlot ──> reconstruction thread ──> hdr_port: Newest[Published] ──> EXR snapshot, state
                                (drops the oldest)                            │
                                                        encoder thread <──────┘  (only while someone
                                                        tone map + JPEG          watches or a snapshot
                                                          │                      is asked)
                                                          ├──> jpeg_port: Newest[EncodedFrame] ──> MJPEG, JPEG snapshot
                                                          └──> preview_port: Newest[PreviewFrame] ──> RTSP

Each stage keeps only the newest item, so a slow stage skips frames instead
of building a queue; every skipped frame is counted by cause. Frame arrival
timestamps (``Frame.host_time_ns``, the monotonic clock) travel with the frames,
so the latency of every stage is measured against the frame's arrival.
numpy and OpenCV release the GIL, so the reconstruction and encoder threads run
on separate cores; OpenCV's own pool is limited (see :func:`opencv_threads`) so
that together they do not oversubscribe the machine.

One role per module:

- ``config``: PipelineConfig and the checks of the run-time settings;
- ``handoff``: Newest (the newest item and its sequence number, sync and async waits: every port) and NewestSlot
  (the capture hand-off, each frame taken once);
- ``meters``: RateMeter, LatencyWindow, DropCounter;
- ``frames``: the records handed on, Published, PreviewFrame (tone-mapped 8-bit) and EncodedFrame;
- ``capture``: CaptureStage (source, reconnects, online/offline);
- ``reconstruction``: ReconstructionStage (a svelive.Reconstructor per camera and method);
- ``colour``: ColourStage (white balance and output space, shared by the preview, so JPEG and RTSP, and the EXR
  snapshot);
- ``encoder``: EncoderStage (tone map once, JPEG for MJPEG watchers, previews for RTSP, no-signal frames,
  its ports, watchers, snapshots);
- ``calibration``: Calibration (response in use, live response calibration, mask) and CalibrationBusy;
- ``pipeline``: Pipeline, which wires the stages and their ports and holds the run-time ``settings()``; the
  outputs (MJPEG, RTSP, snapshots, the state) are made by ``service.publishers`` from its ports.
"""

from service.pipeline.calibration import Calibration, CalibrationBusy
from service.pipeline.capture import CaptureStage
from service.pipeline.colour import ColourStage
from service.pipeline.config import FALLBACK_PATTERN, PipelineConfig, check_jpeg_quality, check_method
from service.pipeline.encoder import EncoderStage, encode_jpeg, no_signal_image
from service.pipeline.frames import EncodedFrame, Published, PreviewFrame, monotonic_to_wall
from service.pipeline.handoff import Newest, NewestSlot
from service.pipeline.meters import WINDOW, DropCounter, LatencyWindow, RateMeter
from service.pipeline.pipeline import Pipeline, opencv_threads
from service.pipeline.reconstruction import ReconstructionStage

__all__ = ["FALLBACK_PATTERN", "WINDOW", "Calibration", "CalibrationBusy", "CaptureStage", "ColourStage", "DropCounter",
           "EncodedFrame", "EncoderStage", "LatencyWindow", "Newest", "NewestSlot", "Pipeline",
           "PipelineConfig", "PreviewFrame", "Published", "RateMeter", "ReconstructionStage", "check_jpeg_quality", "check_method",
           "encode_jpeg", "monotonic_to_wall", "no_signal_image", "opencv_threads"]
