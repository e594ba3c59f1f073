"""The joint reconstruction (svelive.reconstruction.colour, the default mode): chroma, the folded
luminance through the mono method, its refinement and the colour (:func:`joint`), and its parts, which
a stream fuses (:class:`Joint`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from svelive.reconstruction.colour.directional import directional_channels, log_floor
from svelive.reconstruction.colour.folding import colourise, luminance_input
from svelive.reconstruction.colour.interpolate import Interpolation, interpolation
from svelive.reconstruction.colour.lattice import lattice_channels
from svelive.reconstruction.colour.lights import light_colours
from svelive.reconstruction.colour.refinement import refine
from svelive.reconstruction.colour.shares import Chroma, chroma
from svelive.reconstruction.colour.sites import site_chroma as site_chroma_into
from svelive.reconstruction.methods import MethodSpec
from svelive.reconstruction.methods.base import Estimate, SveInput


@dataclass(frozen=True)
class Joint:
    """The joint reconstruction and its parts (a stream fuses them).

    Attributes:
        estimate: the colour Estimate (see :func:`run_colour`).
        luminance_input: the monochrome SVE frame of the luminance (exposures e', SveInput.folded;
            or, for a method that reads only the tile, readings divided by k_c).
        chroma: the frame's chroma.
        interpolation: its interpolation (shares, and the coarse luminance after them when the
            luminance was refined).
        finite: True where every value of the estimate's image was found finite as the passes that wrote it
            (the refinement's colour pass, the lattice) wrote it, the lights stage writing only finite values;
            False: not known.
    """

    estimate: Estimate
    luminance_input: SveInput
    chroma: Chroma
    interpolation: Interpolation
    finite: bool = False


def fold_luminance(inp: SveInput, coarse: bool, exposures: bool, workers: int = 1,
                   ch: Chroma | None = None, whole: bool = False) -> tuple[Chroma, Interpolation, SveInput]:
    """The steps before the mono method (:func:`joint`'s, and a stream's band refresh's): the frame's chroma (``ch``
    where given: a stream's, colour.partial_chroma), its interpolation (with the coarse luminance where ``coarse``;
    ``whole``: interpolation's, where passes after the fold read it too) and the monochrome input of the luminance
    (folded exposures e' with ``exposures``, svelive.reconstruction.colour.folding.luminance_input)."""
    ch = chroma(inp) if ch is None else ch
    inter = interpolation(ch, coarse=coarse, whole=whole)
    return ch, inter, luminance_input(inp, inter, exposures, workers)


def joint(inp: SveInput, spec: MethodSpec, rgb: bool = True, refined: bool = True, site_chroma: bool = False,
          lattice: bool = True, directional: bool = False, variance: bool = True, lights: bool = True,
          **options) -> Joint:
    """The joint reconstruction (package docstring) with the mono method ``spec`` and its ``options``.

    With a method that reports its variance and ``refined``, the luminance is refined at the
    chroma's scale (:func:`refine`); the estimate's variance is then the refined one's, or None with
    ``variance`` False (for a caller that reads only the image: the refined variance is not written).
    ``rgb`` False leaves the colour out (the estimate's image is then the luminance). A stream
    takes neither: it fuses the frames' luminance and chroma, then refines and colours.
    ``site_chroma`` (opt-in, docs/peers.md): with ``rgb``, each
    pixel's colour ratios from its own 3x3 neighbourhood where the noise model supports them
    (svelive.reconstruction.colour.sites; 2x2 Bayer CFAs), the cells' elsewhere. ``lattice`` (default on):
    with ``rgb``, a strongly saturated colour's other channels from their own lattices where a pixel's own
    channel carries almost none of its light (svelive.reconstruction.colour.lattice; 2x2 Bayer CFAs).
    ``directional``: with ``rgb``, after the lattice stage, each pixel's other channels from a directional
    demosaicing of every pixel's own channel in the logarithm where the colour is not strongly saturated
    and the readings are above their noise (svelive.reconstruction.colour.directional; 2x2 Bayer CFAs).
    ``lights`` (default on): with ``rgb``, a small light that clips takes one colour pooled from every site it
    lights instead of the cells' (svelive.reconstruction.colour.lights; any CFA).
    """
    workers = options.get("workers", 1)  # the method's threads serve the colour passes too
    ch, inter, lum = fold_luminance(inp, spec.variance and refined, spec.exposures, workers,
                                    whole=rgb or (spec.variance and refined))
    if spec.variance:
        options = {**options, "return_variance": True}
    est = spec.run(lum, **options)
    luminance, method_variance = est.image, est.variance
    image = finite = None
    if method_variance is not None and refined:  # with rgb, coloured in the refinement's pass (colourise's values)
        refined_variance = np.empty_like(method_variance) if variance else None
        image = np.empty((*luminance.shape, 3), np.float32) if rgb else None
        finite = np.empty(luminance.shape[0], np.bool_) if rgb else None
        luminance = refine(luminance, method_variance, inter, ch.layout.cell, out_variance=refined_variance,
                           new_variance=True, rgb=image, finite=finite, workers=workers)
        method_variance = refined_variance
    elif rgb:
        image = colourise(luminance, inter, workers)
    image = luminance if image is None else image
    if rgb:
        luminance = luminance.copy() if luminance is est.image else luminance  # (the method's own array stays)
        if lattice:
            lattice_channels(inp, luminance, image, ch.shares, ch.layout, workers, finite)
        if lights:
            light_colours(inp, luminance, image, ch.white, ch.layout)
        if directional:
            directional_channels(inp, luminance, image, ch.layout.share, log_floor(inp, ch.layout), workers=workers)
        if site_chroma:
            site_chroma_into(inp, luminance, image, ch.layout.share, workers)
    checked = finite is not None and not directional and not site_chroma and bool(finite.all())
    return Joint(Estimate(image, est.lower_bound, method_variance, luminance, window=est.window), lum, ch, inter,
                 checked)
