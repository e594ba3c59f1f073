"""The shares applied per pixel (svelive.reconstruction.colour, steps b and c): the luminance folded into
a monochrome SVE frame of exposures e' = e k_c (:func:`luminance_input`, :func:`folded_exposure`), and
RGB = Y k_c from the luminance (:func:`colourise`)."""

from __future__ import annotations

from concurrent.futures import Executor
from functools import lru_cache

import numpy as np

from svelive.core.cfa import ColourFilter
from svelive.core.pattern import Pattern
from svelive.jit import kernel
from svelive.reconstruction.colour.interpolate import Interpolation, _pieces
from svelive.reconstruction.methods.base import SveInput, map_on


def folded_exposure(inp: SveInput, inter: Interpolation, workers: int | Executor = 1) -> np.ndarray:
    """e' = e k_c of every pixel, float32 (H, W) (package docstring, step b); ``workers``: base.map_on."""
    out = np.empty(inp.shape, np.float32)
    channel_rows = _channel_rows(inp.cfa, inp.shape[1])
    # a nominal pattern's exposures repeat with its tile's rows: the kernel reads those rows, not a whole frame
    exposure = inp.exposure if inp.pattern.pixel_map is not None else inp.exposure[:inp.pattern.shape[0]]
    paired = inp.cfa.shape[1] <= 2 <= inp.shape[1]  # each row's channels alternate (or are one)

    def piece(rows: slice) -> None:
        planes, first = inter.piece_rows(rows)
        _fold(exposure, channel_rows, rows.start, planes, inter.top[rows] - first, inter.frac[rows], out[rows], paired)

    map_on(workers, piece, _pieces(inp.shape[0]))
    return out


@lru_cache(maxsize=16)
def _channel_rows(cfa: ColourFilter, width: int) -> np.ndarray:
    """The channel of every pixel of the CFA tile's rows, uint8 (th, width), read-only."""
    rows = cfa.channel_map((cfa.shape[0], width))
    rows.setflags(write=False)
    return rows


def colourise(luminance: np.ndarray, inter: Interpolation, workers: int | Executor = 1,
              copy: np.ndarray | None = None) -> np.ndarray:
    """RGB = Y k_c, float32 (H, W, 3), from the luminance Y (H, W) (package docstring, step c). ``copy``:
    float32 (H, W) or None, where Y is copied in the same pass (each row while it is in cache)."""
    out = np.empty((*luminance.shape, 3), np.float32)
    luminance = np.ascontiguousarray(luminance, np.float32)
    none = np.empty((0, 0), np.float32)

    interleaved = out.reshape(luminance.shape[0], -1)  # (H, 3 W): the kernel's stores, one flat row each

    def piece(rows: slice) -> None:
        planes, first = inter.piece_rows(rows)
        _colourise(luminance[rows], planes, inter.top[rows] - first, inter.frac[rows], interleaved[rows],
                   none if copy is None else copy[rows])

    map_on(workers, piece, _pieces(luminance.shape[0]))
    return out


@kernel
def _fold(exposure, channel_rows, first, rows, top, frac, out, paired):
    """out = e k_c of each pixel's channel c (``channel_rows``: the CFA's rows; the arrays' row r is
    frame row ``first`` + r, whose exposures are ``exposure``'s row (``first`` + r) modulo its rows: the
    whole frame's, or a nominal pattern's tile rows), k_c interpolated between the pixel's two cell
    rows. ``paired`` (a CFA of one or two columns, a row of two pixels or more): the row's two channels
    interpolated at every pixel, the pixel's chosen by its column's parity (a loop that vectorises: 3.5
    times faster than a choice by the loaded channel); else the two values of each pixel's channel chosen
    first (every value loaded before the choice), then one interpolation per pixel."""
    period, last = channel_rows.shape[0], rows.shape[1] - 1
    for r in range(out.shape[0]):
        t0, f = top[r], frac[r]
        t1 = min(t0 + 1, last)
        ch, e, o = channel_rows[(first + r) % period], exposure[(first + r) % exposure.shape[0]], out[r]
        if paired:
            c0, c1 = ch[0], ch[1]
            a0, b0, a1, b1 = rows[c0, t0], rows[c0, t1], rows[c1, t0], rows[c1, t1]
            for x in range(o.size):
                k0 = a0[x] + (b0[x] - a0[x]) * f
                k1 = a1[x] + (b1[x] - a1[x]) * f
                o[x] = e[x] * (k0 if x % 2 == 0 else k1)
        else:
            a0, b0, a1, b1, a2, b2 = rows[0, t0], rows[0, t1], rows[1, t0], rows[1, t1], rows[2, t0], rows[2, t1]
            for x in range(o.size):
                c, p0, p1, p2, q0, q1, q2 = ch[x], a0[x], a1[x], a2[x], b0[x], b1[x], b2[x]
                a = p0 if c == 0 else (p1 if c == 1 else p2)
                b = q0 if c == 0 else (q1 if c == 1 else q2)
                o[x] = e[x] * (a + (b - a) * f)


@kernel
def _colourise(luminance, rows, top, frac, out, copy):
    """out (H, 3 W), the rows of (H, W, 3) = Y k_c, the shares interpolated between each row's two
    cell rows in the loop. Stores into flat rows: into (H, W, 3) the loop does not vectorise (25 %
    slower). ``copy`` (H, W), unless empty: the luminance's rows copied there."""
    last = rows.shape[1] - 1
    for r in range(luminance.shape[0]):
        t0, f = top[r], frac[r]
        t1 = min(t0 + 1, last)
        _colour_row(luminance[r], rows[0, t0], rows[0, t1], rows[1, t0], rows[1, t1], rows[2, t0], rows[2, t1], f,
                    out[r])
        if copy.size > 0:
            copy[r] = luminance[r]


@kernel(inline="always")
def _colour_row(y, a0, b0, a1, b1, a2, b2, f, o):
    """o (3 W,) = one row of (W, 3) RGB = ``y`` (W,) times each channel's share interpolated at ``f``
    between its two cell rows (``a``, ``b``; (W,) each)."""
    for x in range(y.size):
        _colour_pixel(y[x], a0, b0, a1, b1, a2, b2, f, o, x)


@kernel(inline="always")
def _finite_row(row):
    """Whether every value of ``row`` (float32, 1-D) is finite: read while the row is in cache, the check of a
    whole frame takes a tenth of numpy's sum over it from memory (a loop of comparisons that vectorises)."""
    bad = False
    for x in range(row.size):
        bad |= not np.isfinite(row[x])
    return not bad


@kernel(inline="always")
def _colour_pixel(v, a0, b0, a1, b1, a2, b2, f, o, x):
    """o[3 x:3 x + 3] = RGB of pixel ``x`` of a row of :func:`_colour_row`, its luminance ``v``."""
    o[3 * x] = v * (a0[x] + (b0[x] - a0[x]) * f)
    o[3 * x + 1] = v * (a1[x] + (b1[x] - a1[x]) * f)
    o[3 * x + 2] = v * (a2[x] + (b2[x] - a2[x]) * f)


def luminance_input(inp: SveInput, inter: Interpolation, exposures: bool = True,
                    workers: int | Executor = 1) -> SveInput:
    """The monochrome SVE frame of the luminance: exposures e' (``exposures``, folded) or, for a
    method that reads only the pattern's tile, readings s e / e' with the nominal exposures."""
    folded = folded_exposure(inp, inter, workers)
    if exposures:  # a calibrated map is in e' already: the nominal tile keeps the method's strips
        pattern = inp.pattern if inp.pattern.pixel_map is None else Pattern(inp.pattern.tile)
        return SveInput(inp.signal, folded, inp.censored, pattern, inp.sensor, inp.integral, folded=True)
    signal = inp.signal * inp.exposure
    signal /= folded
    return SveInput(signal, inp.exposure, inp.censored, inp.pattern, inp.sensor, False)
