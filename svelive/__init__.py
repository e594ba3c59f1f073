"""svelive: HDR video from cameras with spatially varying pixel exposures (SVE)."""

from svelive.errors import SveliveError
from svelive.frame import Frame, HdrFrame
from svelive.pattern import Pattern
from svelive.sensor import Sensor

__all__ = ["Frame", "HdrFrame", "Pattern", "Sensor", "SveliveError"]
