"""Reconstruction methods, one module each, all behind ``run(inp: SveInput, **options) -> Estimate``.

METHODS lists them by name, the default first. Each entry declares what the
method can do, so that callers never inspect its signature.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

from svelive.core.errors import SveliveError
from svelive.reconstruction.methods import adaptive, aggregate, cubic, weighted
from svelive.reconstruction.methods.base import Estimate, SveInput


@dataclass(frozen=True)
class MethodSpec:
    """One reconstruction method and its capabilities.

    Attributes:
        name: the name users choose it by.
        run: ``run(inp, **options) -> Estimate``.
        options: the keyword options a user may pass.
        variance: it returns its own predicted variance when called with ``return_variance=True``.
        workers: it splits a frame over threads when called with ``workers=`` (a count or an Executor).
        exposures: it reads every pixel's exposure from ``SveInput.exposure`` (so takes per-pixel
            exposures, SveInput.folded); False: only the pattern's tile.
        window: it can make the motion tests' window mean in its own pass when called with
            ``window=True`` (``Estimate.window``; None where it cannot for this frame).
        summary: one line for ``svelive methods``.
    """

    name: str
    run: Callable[..., Estimate]
    options: frozenset[str] = frozenset()
    variance: bool = False
    workers: bool = False
    exposures: bool = True
    window: bool = False
    summary: str = ""

    @property
    def accepted(self) -> frozenset[str]:
        """Every keyword ``run`` takes: the user options plus the capability keywords."""
        return self.options | {name for name, has in (("return_variance", self.variance),
                                                      ("workers", self.workers), ("window", self.window)) if has}

    def check_options(self, options: Mapping[str, object]) -> None:
        """Raise a one-line SveliveError naming any keyword ``run`` does not take."""
        unknown = set(options) - self.accepted
        if unknown:
            raise SveliveError(f"method {self.name!r} has no option {', '.join(sorted(unknown))}"
                               f" (it takes: {', '.join(sorted(self.options)) or 'none'})")


METHODS: dict[str, MethodSpec] = {spec.name: spec for spec in (
    MethodSpec("adaptive", adaptive.run, variance=True, workers=True, window=True,
               summary="own reading where neighbours disagree beyond noise, noise-optimal mean where they agree"),
    MethodSpec("weighted", weighted.run, variance=True, workers=True,
               summary="per-exposure interpolation merged with Poisson-Gaussian inverse-variance weights"),
    MethodSpec("aggregate", aggregate.run, workers=True, exposures=False,
               summary="the paper's section 6.1: tile box mean, inverse of the piecewise-linear response"),
    MethodSpec("cubic", cubic.run, options=frozenset({"dark_level", "literal"}),
               summary="the paper's section 6.2: off-grid cubic interpolation by local pseudo-inverse"),
)}

DEFAULT_METHOD = next(iter(METHODS))

__all__ = ["METHODS", "DEFAULT_METHOD", "MethodSpec", "Estimate", "SveInput"]
