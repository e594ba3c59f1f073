"""svelive: HDR video from cameras with spatially varying pixel exposures (SVE)."""

from importlib.metadata import PackageNotFoundError, version as _version

#: The version when svelive runs from a source tree without being installed (keep it pyproject.toml's).
_SOURCE_VERSION = "0.1.0"
try:
    __version__: str = _version("svelive")
except PackageNotFoundError:
    __version__ = _SOURCE_VERSION

from svelive.errors import SveliveError
from svelive.camera import Camera
from svelive.cfa import ColourFilter
from svelive.frame import Frame, HdrFrame
from svelive.pattern import Pattern
from svelive.sensor import Sensor
from svelive.reconstruction import Reconstructor, methods, reconstruct, reconstruct_sequence
from svelive.simulate import SimulatedFrame, simulate

__all__ = ["__version__", "Camera", "ColourFilter", "Frame", "HdrFrame", "Pattern", "Sensor", "SveliveError", "methods",
           "reconstruct", "simulate", "SimulatedFrame", "Reconstructor", "reconstruct_sequence"]
