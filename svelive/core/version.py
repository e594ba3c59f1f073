"""svelive's version: the installed distribution's, or the source tree's when it runs uninstalled."""

from importlib.metadata import PackageNotFoundError
from importlib.metadata import version as _version

#: The version when svelive runs from a source tree without being installed (keep it pyproject.toml's).
SOURCE_VERSION = "0.1.0"
try:
    __version__: str = _version("svelive")
except PackageNotFoundError:
    __version__ = SOURCE_VERSION
