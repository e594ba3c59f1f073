"""The public entry of colour reconstruction: :func:`run_colour` in either mode, joint or split
(svelive.reconstruction.colour)."""

from __future__ import annotations

from svelive.core.errors import SveliveError
from svelive.reconstruction.colour.joint_parts import joint
from svelive.reconstruction.colour.split_baseline import split
from svelive.reconstruction.methods import MethodSpec
from svelive.reconstruction.methods.base import Estimate, SveInput

MODES = ("joint", "split")


def run_colour(inp: SveInput, spec: MethodSpec, mode: str, variance: bool = True,
               **options) -> tuple[Estimate, bool]:
    """Reconstruct a colour frame (``inp.cfa`` set) with the mono method ``spec``.

    Args:
        inp: a prepared colour frame (svelive.reconstruction.input.prepare).
        spec: the monochrome method, with ``options`` (its own, plus ``return_variance``
            and ``workers`` where it has them).
        mode: ``"joint"`` or ``"split"`` (package docstring).
        variance: False where only the image is read: joint's refined variance is then not written
            (the estimate's is None; joint_parts.joint).

    Returns:
        (estimate, finite): Estimate with ``image`` float32 (H, W, 3) linear camera RGB (DN at exposure 1 per
        channel, before white balance), ``luminance`` float32 (H, W), the luminance
        Y = sum_c n_c RGB_c, and ``lower_bound`` (H, W) and ``variance`` (H, W) of it; ``finite`` True where
        the passes that wrote the image found every value finite (joint_parts.Joint.finite), False: not known.
    """
    if inp.cfa is None:
        raise SveliveError("run_colour needs a colour frame: give the colour filter (cfa='RGGB')")
    if mode == "joint":
        parts = joint(inp, spec, variance=variance, **options)
        return parts.estimate, parts.finite
    if mode == "split":
        return split(inp, spec, **options), False
    raise SveliveError(f"unknown colour mode {mode!r}; choose from {', '.join(MODES)}")
