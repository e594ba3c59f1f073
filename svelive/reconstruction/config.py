"""Thresholds of the per-pixel motion tests (svelive.reconstruction.consistency and .fusion)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from svelive.errors import SveliveError


@dataclass(frozen=True)
class MotionConfig:
    """Thresholds of the motion tests.

    Attributes:
        temporal_sigmas: k of the frame-to-history test; 4 gives a Gaussian
            false-alarm rate of 6e-5 per pixel before widening.
        consistency_sigmas: k of the within-frame exposure-consistency test.
        max_history: frames a static pixel averages at most (the memory of the
            recursive average once full: its weight for a new frame is 1 / max_history).
        widen: pixels by which flagged areas grow (a square of 2 widen + 1).
        detail_sigmas: how far beyond its noise a pixel's own fused readings must
            differ from the smooth estimate before they sharpen it (:func:`sharpen`).
        global_motion: fraction of moving pixels above which the whole history restarts.
        compensate_illumination: divide out a global brightness ratio between
            history and frame before testing.
    """

    temporal_sigmas: float = 4.0
    consistency_sigmas: float = 4.0
    max_history: int = 8
    widen: int = 1
    detail_sigmas: float = 3.0
    global_motion: float = 0.5
    compensate_illumination: bool = True

    def __post_init__(self) -> None:
        for name in ("temporal_sigmas", "consistency_sigmas", "detail_sigmas"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise SveliveError(f"motion config: {name} must be > 0, got {value}")
        if int(self.max_history) < 1:
            raise SveliveError(f"motion config: max_history must be >= 1, got {self.max_history}")
        if not 0 <= int(self.widen) <= 16:
            raise SveliveError(f"motion config: widen must be 0..16 pixels, got {self.widen}")
