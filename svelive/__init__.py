"""svelive: HDR video from cameras with spatially varying pixel exposures (SVE)."""

from svelive.errors import SveliveError
from svelive.camera import Camera
from svelive.cfa import ColourFilter
from svelive.frame import Frame, HdrFrame
from svelive.pattern import Pattern
from svelive.sensor import Sensor
from svelive.reconstruction import Reconstructor, methods, reconstruct, reconstruct_sequence
from svelive.simulate import SimulatedFrame, simulate

__all__ = ["Camera", "ColourFilter", "Frame", "HdrFrame", "Pattern", "Sensor", "SveliveError", "methods",
           "reconstruct", "simulate", "SimulatedFrame", "Reconstructor", "reconstruct_sequence"]
