"""The ``svelive`` command.

Each verb is a small function over the library. This package holds the command
line: the parser and ``main`` here, and one module per group of verbs, each with
``add_commands(subparsers)``, listed in COMMAND_MODULES: ``reconstruct`` (info,
methods, simulate, reconstruct, demo), ``calibrate``, ``capture`` (record,
replay-info, export), ``motion`` (reconstruct-sequence), ``bench``. The ``serve``
verb stays in ``service/commands.py``, loaded by name, so that svelive imports
nothing of service. Every library error reaches the user as one line on stderr
and exit status 2.
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import sys
from pathlib import Path

import numpy as np

from svelive.core.errors import SveliveError

#: Modules that add verbs of their own: each defines add_commands(subparsers).
COMMAND_MODULES: tuple[str, ...] = (
    "svelive.cli.reconstruct",
    "svelive.cli.calibrate",
    "svelive.cli.capture",
    "svelive.cli.motion",
    "service.commands",  # by name: svelive imports nothing of service
    "svelive.cli.bench",
)


def build_parser() -> argparse.ArgumentParser:
    from svelive import __version__

    parser = argparse.ArgumentParser(prog="svelive", description="HDR video from spatially varying exposure (SVE) cameras.")
    parser.add_argument("--version", action="version", version=f"svelive {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).add_commands(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    from replay.reader import show_warnings_plainly

    show_warnings_plainly()  # a damaged recording's warnings as one plain line each
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except SveliveError as exc:
        print(f"svelive {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


def print_json(data: object) -> None:
    """Print ``data`` as indented JSON (numpy scalars become numbers)."""
    print(json.dumps(data, indent=2, default=lambda o: o.item() if isinstance(o, np.generic) else str(o)))


def existing_file(text: str) -> Path:
    """argparse type: a path that must name an existing regular file."""
    path = Path(text)
    if not path.is_file():
        raise argparse.ArgumentTypeError(f"{text}: no such file" if not path.exists() else f"{text}: not a file")
    return path


def parse_times(text: str) -> list[float]:
    """argparse type of --exposure-times: comma-separated positive numbers, all different."""
    try:
        times = [float(t) for t in text.split(",") if t.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: exposure times are numbers separated by commas, "
                                         "e.g. 10000,15000") from None
    if not times or not all(math.isfinite(t) and t > 0 for t in times):
        raise argparse.ArgumentTypeError(f"{text!r}: exposure times must be positive numbers")
    if len(set(times)) < len(times):  # as the live sweep refuses them: equal times give the fit nothing
        raise argparse.ArgumentTypeError(f"{text!r}: exposure times must differ")
    return times

