"""Frame sources: live cameras, image sequences, recordings and a synthetic demo.

``open_source(spec, **opts)`` builds a :class:`Source` from a spec string:

=====================  =====================================================
``gige[:DEVICE_ID]``   GigE Vision camera through Aravis (the first one found,
                       opened by its address, or by id, serial, or IP address)
``v4l2:/dev/videoN``   V4L2 device through OpenCV in raw mode
``images:GLOB_OR_DIR`` 8/16-bit PNG, TIFF or PGM files in name order
``replay:PATH``        an svelive recording
``demo``               synthetic colour SVE camera filming a shipped HDR image
=====================  =====================================================

Options are keyword arguments understood by the source's config dataclass
(e.g. ``fps=30, loop=True`` for images, ``speed=2.0`` for replay,
``pixel_format="Mono12Packed", width=1280`` for cameras) plus ``pattern``,
``cfa`` (colour filter layout, ``"none"`` for monochrome; a Bayer pixel format
sets it by itself, see :func:`svelive.capture.source.resolve_cfa`) and
``sensor`` (a Sensor or ``bits``/``black_level``/``white_level``) for all.
Unknown options are an error naming the accepted ones. The source modules are
imported lazily, so Aravis (PyGObject) is only needed for ``gige``.
"""

from __future__ import annotations

import dataclasses
import importlib
from typing import Any

from svelive.capture.source import AfterChange, EndOfStream, Source
from svelive.core.errors import SveliveError
from svelive.core.sensor import Sensor

__all__ = ["AfterChange", "EndOfStream", "KINDS", "Source", "open_source", "parse_spec"]

#: spec prefix -> (module, class name, whether the part after ':' is required)
KINDS: dict[str, tuple[str, str, bool]] = {
    "gige": ("svelive.capture.gige", "GigeSource", False),
    "v4l2": ("svelive.capture.v4l2", "V4l2Source", True),
    "images": ("svelive.capture.images", "ImageSequenceSource", True),
    "replay": ("svelive.capture.replay", "ReplaySource", True),
    "demo": ("svelive.capture.demo", "DemoSource", False),
}


def parse_spec(spec: str) -> tuple[str, str | None]:
    """Split ``"kind:argument"`` into (kind, argument or None), checking the kind."""
    if not isinstance(spec, str) or not spec.strip():
        raise SveliveError("source spec is empty; use one of " + ", ".join(_usage()))
    kind, sep, arg = spec.strip().partition(":")
    kind = kind.lower()
    if kind not in KINDS:
        raise SveliveError(f"unknown source {spec!r}; use one of " + ", ".join(_usage()))
    arg = arg.strip() if sep else None
    if KINDS[kind][2] and not arg:
        raise SveliveError(f"source {kind!r} needs an argument: {dict(zip(KINDS, _usage()))[kind]}")
    return kind, arg or None


def _usage() -> list[str]:
    return ["gige[:DEVICE_ID]", "v4l2:/dev/videoN", "images:GLOB_OR_DIR", "replay:PATH", "demo"]


def build_sensor(sensor: Sensor | None, bits: int | None, black_level: float | None,
                 white_level: float | None, default_bits: int) -> Sensor:
    """The Sensor for a source: the one given, or one from bits/black/white (missing ones defaulted)."""
    if sensor is not None:
        return sensor
    return Sensor(bits=int(bits) if bits is not None else default_bits,
                  black_level=float(black_level or 0.0), white_level=white_level)


def make_config(cls: type, opts: dict[str, Any], where: str) -> Any:
    """Instantiate config dataclass ``cls`` from ``opts``; unknown keys are a one-line error."""
    fields = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(k for k, v in opts.items() if k not in fields and v is not None)
    if unknown:
        raise SveliveError(f"{where}: unknown option(s) {', '.join(unknown)}; accepted: {', '.join(sorted(fields))}")
    return cls(**{k: v for k, v in opts.items() if k in fields and v is not None})


def open_source(spec: str, **opts: Any) -> Source:
    """Build (not yet open) the source for ``spec``; open it with ``with`` or ``.open()``.

    Options whose value is None are ignored, so CLI arguments can be passed through.
    """
    kind, arg = parse_spec(spec)
    module, cls_name, _ = KINDS[kind]
    cls = getattr(importlib.import_module(module), cls_name)
    return cls(spec.strip(), arg, **opts)
