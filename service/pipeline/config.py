"""What the pipeline reconstructs and how: :class:`PipelineConfig` and the checks of its run-time settings."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from svelive.capture import Source, open_source
from svelive.capture.source import MONO_WORDS
from svelive.core.camera import Camera
from svelive.core.cfa import ColourFilter
from svelive.core.errors import SveliveError
from svelive.options import CameraSettings
from svelive.reconstruction.live import LIVE_REFRESH, check_live_quality
from svelive.reconstruction.single import methods as method_names
from svelive.tonemap import ToneSettings
from svelive.whitebalance import ColourSettings

#: Pattern used when neither the settings nor the source name one.
FALLBACK_PATTERN = "1,4/16,64"


@dataclass(frozen=True)
class PipelineConfig:
    """What the pipeline reconstructs and how.

    Attributes:
        source: source spec (see svelive.capture), e.g. ``"demo"`` or ``"gige:GV01"``.
        source_options: extra keyword options for ``open_source`` (e.g. fps, width).
        pattern: exposure pattern text; None: the source's own, else FALLBACK_PATTERN.
        cfa: colour filter layout (svelive.core.cfa), ``"none"`` for explicitly monochrome, or
            None: the source's pixel format says (a Bayer format sets it by itself).
        black_level, white_level: DN overrides of the source's sensor; None keeps it.
        method: reconstruction method name; None for the default.
        temporal: use temporal fusion where the reconstructor offers it.
        live_quality: ``adaptive``: while the reconstruction cannot keep the camera's rate, step down the
            declared ladder of cheaper live settings and back up with headroom (service.pipeline.quality);
            ``fixed``: always the configured method and fusion.
        response: path of a response JSON (``svelive calibrate response``): every frame
            is linearised through it before reconstruction; None: the camera is linear.
        mask: path of a mask file (``svelive calibrate mask``): its per-pixel exposure
            map replaces the nominal tile's exposures; None: the nominal pattern.
        workers: threads the reconstruction uses; 0: one per core.
        parallel_frames: frames reconstructed at once (1..4), the threads shared out among them; fused
            and published in arrival order. 1: each frame spread over every thread (the lowest
            latency); 2: more frames per second when the cores are otherwise free, at the latency of
            a frame on fewer threads (measured in docs/service.md).
        refresh: streams with fusion and ``adaptive``, monochrome and colour: run the method per frame only on the
            bands whose history needs it and a round-robin 1 / ``refresh`` of the settled ones (``Reconstructor(
            refresh=..., colour_refresh=True)``, once the noise model is trusted; a colour stream's bands are its
            folded luminance's); 0: every band every frame.
        queue: frames the capture -> reconstruction hand-off holds (1..8).
        tone: preview tone-mapping parameters.
        colour: colour output of a colour camera (svelive.whitebalance.ColourSettings: white
            balance, camera -> Rec.709 matrix, the space EXR snapshots are in); unused for mono.
        jpeg_quality: preview JPEG quality, 10..100.
        preview_width: downscale previews wider than this (pixels); 0 keeps full size.
        publisher_nice: nice levels the publishers' threads (tone map and JPEG, RTSP conversion and H.264) run below
            the capture and reconstruction (service.pipeline.priority); 0: the same priority.
        publisher_idle: run the preview encoder's thread under Linux's ``SCHED_IDLE`` policy as well: only on a
            core the capture and reconstruction leave idle, where the thread may leave the policy again and for as
            long as it gets a core in time (service.pipeline.priority.EncoderPriority); off by default (measured:
            the same frame rate a client within the spread, more latency; docs/benchmarks.md).
        offline_after_s: no frame for this long means the source is offline.
        retry_s: wait before reopening a source that failed or went away.
        no_signal_fps: rate of "no signal" frames sent while the source is offline.
    """

    source: str = "demo"
    source_options: dict[str, Any] = field(default_factory=dict)
    pattern: str | None = None
    cfa: str | None = None
    black_level: float | None = None
    white_level: float | None = None
    method: str | None = None
    temporal: bool = True
    live_quality: str = "adaptive"
    response: str | None = None
    mask: str | None = None
    workers: int = 0
    parallel_frames: int = 1
    refresh: int = LIVE_REFRESH
    queue: int = 1
    tone: ToneSettings = field(default_factory=ToneSettings)
    colour: ColourSettings = field(default_factory=ColourSettings)
    jpeg_quality: int = 80
    preview_width: int = 0
    publisher_nice: int = 5
    publisher_idle: bool = False
    offline_after_s: float = 2.0
    retry_s: float = 1.0
    no_signal_fps: float = 2.0

    def __post_init__(self) -> None:
        if self.pattern is not None:
            Camera.build(self.pattern, self.cfa if self.cfa not in MONO_WORDS else None)
        elif self.cfa is not None and self.cfa not in MONO_WORDS:
            ColourFilter.parse(self.cfa)
        check_method(self.method)
        check_live_quality(self.live_quality)
        check_jpeg_quality(self.jpeg_quality)
        if not 0 <= self.workers <= 64:
            raise SveliveError(f"workers must be 0..64 (0: one per core), got {self.workers}")
        if isinstance(self.parallel_frames, bool) or not isinstance(self.parallel_frames, int) \
                or not 1 <= self.parallel_frames <= 4:
            raise SveliveError(f"parallel_frames must be 1..4, got {self.parallel_frames!r}")
        if isinstance(self.refresh, bool) or not isinstance(self.refresh, int) or not 0 <= self.refresh <= 64:
            raise SveliveError(f"refresh must be 0..64 (0: off), got {self.refresh!r}")
        if not 1 <= self.queue <= 8:
            raise SveliveError(f"queue must hold 1..8 frames, got {self.queue}")
        if not 0 <= self.preview_width <= 16384:
            raise SveliveError(f"preview width must be 0..16384 pixels, got {self.preview_width}")
        if isinstance(self.publisher_nice, bool) or not isinstance(self.publisher_nice, int) \
                or not 0 <= self.publisher_nice <= 19:
            raise SveliveError(f"publisher_nice must be 0..19 nice levels, got {self.publisher_nice!r}")
        if not isinstance(self.publisher_idle, bool):
            raise SveliveError(f"publisher_idle must be true or false, got {self.publisher_idle!r}")
        for name in ("offline_after_s", "retry_s", "no_signal_fps"):
            if not 0 < getattr(self, name) <= 3600:
                raise SveliveError(f"{name} must be in (0, 3600], got {getattr(self, name)}")


    def build_source(self) -> Source:
        """The configured source, built (not opened): its spec with the camera options (svelive.options, as every
        verb reads them) and the source's own options."""
        return open_source(self.source, **{**CameraSettings.from_mapping(self).source_options(),
                                           **self.source_options})


def check_method(method: str | None) -> None:
    """Raise SveliveError unless ``method`` is None or a known reconstruction method."""
    if method is not None and method not in method_names():
        raise SveliveError(f"unknown method {method!r}; choose from {', '.join(method_names())}")


def check_jpeg_quality(quality: int) -> None:
    """Raise SveliveError unless ``quality`` is an integer JPEG quality in 10..100."""
    if isinstance(quality, bool) or not isinstance(quality, (int, np.integer)) or not 10 <= quality <= 100:
        raise SveliveError(f"JPEG quality must be an integer 10..100, got {quality!r}")
