"""svelive: HDR video from cameras with spatially varying pixel exposures (SVE)."""

from svelive.core.camera import Camera
from svelive.core.cfa import ColourFilter
from svelive.core.errors import SveliveError
from svelive.core.frame import Frame, HdrFrame
from svelive.core.pattern import Pattern
from svelive.core.sensor import Sensor
from svelive.core.version import __version__
from svelive.reconstruction import Reconstructor, reconstruct, reconstruct_sequence
from svelive.reconstruction.single import methods
from svelive.simulation import SimulatedFrame, simulate

__all__ = ["__version__", "Camera", "ColourFilter", "Frame", "HdrFrame", "Pattern", "Sensor", "SveliveError", "methods",
           "reconstruct", "simulate", "SimulatedFrame", "Reconstructor", "reconstruct_sequence"]
