"""The camera options of the command line, defined once: ``--pattern``, ``--cfa``, ``--bits``,
``--black-level``, ``--white-level``.

Every verb adds the ones it takes with :func:`add_camera_option` (the flag, its type and the name
it is read by are here; the verb says what the option means for it: help, default, whether it is
required). What the user gave is read back as one :class:`CameraSettings`, from parsed arguments
or from a settings table (a TOML camera table, the service's settings), and becomes a Camera
(:func:`build_camera`, for verbs that read files) or the options of a source
(:meth:`CameraSettings.source_options`, for verbs and services that open one), the same way
whichever of the three it came from.
"""

from __future__ import annotations

import argparse
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

from svelive.capture.source import MONO_WORDS
from svelive.core.camera import Camera
from svelive.core.errors import SveliveError
from svelive.core.sensor import Sensor

#: The camera options: setting name -> (command-line flag, value type).
CAMERA_OPTIONS: dict[str, tuple[str, type]] = {
    "pattern": ("--pattern", str),
    "cfa": ("--cfa", str),
    "bits": ("--bits", int),
    "black_level": ("--black-level", float),
    "white_level": ("--white-level", float),
}

#: What --cfa means to the verbs that open a source (record, reconstruct-sequence, serve).
SOURCE_CFA_HELP = ("colour filter layout, e.g. RGGB or quad-RGGB; 'none' for monochrome "
                   "(default: a Bayer pixel format sets it by itself)")


def add_camera_option(p: argparse.ArgumentParser, name: str, help: str | None = None, *, default: Any = None,
                      required: bool = False, metavar: str | None = None) -> None:
    """Add the camera option ``name`` (a key of :data:`CAMERA_OPTIONS`) to a verb's parser, read back as
    ``args.<name>``; ``help``, ``default``, ``required`` and ``metavar`` are the verb's."""
    flag, kind = CAMERA_OPTIONS[name]
    extra: dict[str, Any] = {} if kind is str else {"type": kind}
    if required:
        extra["required"] = True
    if metavar is not None:
        extra["metavar"] = metavar
    p.add_argument(flag, dest=name, default=default, help=help, **extra)


@dataclass(frozen=True)
class CameraSettings:
    """The camera the user described; None: not given (the source's, the file's or the default).

    Attributes:
        pattern: exposure pattern text, a preset or a colour layout (``dual-iso``: sets ``cfa`` too).
        cfa: colour filter text, or ``"none"``/``"mono"`` for an explicitly monochrome sensor.
        bits: bit depth of the raw values.
        black_level, white_level: DN.
    """

    pattern: str | None = None
    cfa: str | None = None
    bits: int | None = None
    black_level: float | None = None
    white_level: float | None = None

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> CameraSettings:
        """The camera options of parsed arguments (those a verb does not take are None)."""
        return cls(**{f.name: getattr(args, f.name, None) for f in fields(cls)})

    @classmethod
    def from_mapping(cls, table: Mapping[str, Any] | Any) -> CameraSettings:
        """The camera settings of a mapping (a TOML table) or of an object with these attributes
        (service.pipeline.PipelineConfig); other keys are ignored."""
        get = table.get if isinstance(table, Mapping) else (lambda name, default: getattr(table, name, default))
        return cls(**{f.name: get(f.name, None) for f in fields(cls)})

    def source_options(self) -> dict[str, Any]:
        """The keyword options of svelive.capture.open_source that say this camera (None ones included:
        a source fills them)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @property
    def colour_filter(self) -> str | None:
        """``cfa`` as a colour filter text for Camera.build: None for not given, ``none`` or ``mono``."""
        return parse_cfa(self.cfa)


def parse_cfa(text: str | None) -> str | None:
    """A --cfa value as a colour filter text for Camera.build: None for not given, 'none' or 'mono'."""
    if text is None or text.strip().lower() in MONO_WORDS:
        return None
    return text


def build_camera(settings: CameraSettings, sensor: Sensor | None = None) -> Camera:
    """The camera of ``settings``' pattern and colour filter (Camera.build) with ``sensor``. ``--cfa none``
    with a colour layout (``dual-iso``) is refused with the line ``svelive serve`` gives: without this check
    the layout's filter won silently and the command wrote colour."""
    camera = Camera.build(settings.pattern, settings.colour_filter, *([sensor] if sensor is not None else []))
    if settings.cfa is not None and settings.colour_filter is None and camera.cfa is not None:
        raise SveliveError(f"the layout {settings.pattern} has the colour filter {camera.cfa.name}, but --cfa "
                           f"{settings.cfa} was given: drop --cfa, or give the exposure pattern itself")
    return camera
