"""Thresholds of the per-pixel motion tests (svelive.reconstruction.consistency and .fusion)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from svelive.core.errors import SveliveError


@dataclass(frozen=True)
class MotionConfig:
    """Thresholds of the motion tests.

    Attributes:
        temporal_sigmas: k of the frame-to-history test; 4 gives a Gaussian
            false-alarm rate of 6e-5 per pixel before widening.
        consistency_sigmas: k of the within-frame exposure-consistency test.
        max_history: frames a static pixel averages at most (the memory of the
            recursive average once full: its weight for a new frame is 1 / max_history).
        widen: pixels by which flagged areas grow (a square of 2 widen + 1). 2: the default
            method's estimate of a pixel reads the readings two pixels away (step 3 sums, over
            a 3x3 window, residuals against 3x3 neighbour estimates), so a pixel next to the
            flagged ones, whose own change is below the test, still reads changed readings:
            with 1, Beachball 5 stops under lost 0.54 dB on moving pixels, with 2 0.21
            (docs/motion.md).
        detail_sigmas: how far beyond its noise a pixel's own fused readings must
            differ from the smooth estimate before they sharpen it (:func:`sharpen`).
        global_motion: fraction of moving pixels above which the whole history restarts.
        global_sigmas: the camera-motion test's per-pixel significance: the whole history
            also restarts when more than ``global_motion`` of the (subsampled, measured)
            pixels differ from their history by more than this many noise standard
            deviations. 1.645 is the 90th percentile of a static pixel's difference: a
            static frame has 10 % beyond it, 34 % if the noise model underestimates the
            variance 3x, both far from half the frame; a camera pan whose changes are each
            below the per-pixel threshold but present everywhere passes it.
        compensate_illumination: divide out a global brightness ratio between
            history and frame before testing.
    """

    temporal_sigmas: float = 4.0
    consistency_sigmas: float = 4.0
    max_history: int = 8
    widen: int = 2
    detail_sigmas: float = 3.0
    global_motion: float = 0.5
    global_sigmas: float = 1.645
    compensate_illumination: bool = True

    def __post_init__(self) -> None:
        for name in ("temporal_sigmas", "consistency_sigmas", "detail_sigmas", "global_sigmas"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise SveliveError(f"motion config: {name} must be > 0, got {value}")
        if int(self.max_history) < 1:
            raise SveliveError(f"motion config: max_history must be >= 1, got {self.max_history}")
        if not 0 <= int(self.widen) <= 16:
            raise SveliveError(f"motion config: widen must be 0..16 pixels, got {self.widen}")
