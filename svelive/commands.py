"""Core verbs of the svelive command: info, methods, simulate, reconstruct, demo."""

from __future__ import annotations

import argparse


def add_commands(sub: argparse._SubParsersAction) -> None:
    pass
