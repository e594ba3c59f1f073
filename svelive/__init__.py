"""svelive: HDR video from cameras with spatially varying pixel exposures (SVE)."""

from svelive.errors import SveliveError
from svelive.frame import Frame, HdrFrame
from svelive.pattern import Pattern
from svelive.sensor import Sensor

__all__ = ["Frame", "HdrFrame", "Pattern", "Sensor", "SveliveError"]

from svelive.reconstruct import methods, reconstruct  # noqa: E402
from svelive.simulate import SimulatedFrame, simulate  # noqa: E402

__all__ += ["methods", "reconstruct", "simulate", "SimulatedFrame"]
from svelive.reconstructor import Reconstructor, reconstruct_sequence  # noqa: E402
__all__ += ["Reconstructor", "reconstruct_sequence"]
