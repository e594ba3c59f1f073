"""Reconstruction methods, one module each, all behind ``run(inp: SveInput, **options) -> Estimate``.

METHODS lists them by name, the default first.
"""

from __future__ import annotations

from typing import Callable

from svelive.methods import adaptive, aggregate, cubic, weighted
from svelive.methods.base import Estimate, SveInput

METHODS: dict[str, Callable[..., Estimate]] = {
    "adaptive": adaptive.run,
    "weighted": weighted.run,
    "aggregate": aggregate.run,
    "cubic": cubic.run,
}

DEFAULT_METHOD = next(iter(METHODS))

__all__ = ["METHODS", "DEFAULT_METHOD", "Estimate", "SveInput"]
