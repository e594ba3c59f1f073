"""From cells to pixels: a chroma's planes interpolated bilinearly from the cells' centres, along rows to
every column (bit for bit OpenCV's linear resize) and, per frame row, between the two cell rows around it
(:class:`Interpolation`); and the pieces of rows the per-pixel passes are spread over threads in."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property, lru_cache

import cv2
import numpy as np
from svelive.jit import fma32, kernel
from svelive.reconstruction.colour.shares import Chroma


@dataclass(frozen=True)
class Interpolation:
    """A chroma's shares interpolated bilinearly from the cells' centres: along rows to every
    column, and for each frame row the two cell rows around it.

    Attributes:
        cells: the planes at the cells' centres, float32 (P_i, Hc, Wc) each, P in all: k_R, k_G, k_B,
            then (with the coarse luminance) L and its variance.
        cx: the cells' columns.
        width: W, the frame's columns.
        top: intp (H,), the cell row at or above each frame row, clamped.
        frac: float32 (H,), the weight of the cell row below (``top`` + 1), 0 at the edges.
    """

    cells: tuple[np.ndarray, ...]
    cx: int
    width: int
    top: np.ndarray
    frac: np.ndarray

    @cached_property
    def rows(self) -> np.ndarray:
        """float32 (P, Hc, W): the planes on the cell rows at every column (made on first use)."""
        return _full_width(self.cells, self.cx, self.width)

    def piece_rows(self, rows: slice) -> tuple[np.ndarray, int]:
        """The planes at every column on the cell rows that frame rows ``rows`` (a non-empty slice) lie
        between, float32 (P, N, W), and the cell row of the first: :attr:`rows` and 0 where made
        (``interpolation(..., whole=True)``), else those cell rows alone, made here into an array that stays in
        cache for the pass over ``rows`` (whole planes written before a pass and read back by it cost a
        stream's refinement about 0.5 ms a colour frame)."""
        if "rows" in self.__dict__:
            return self.rows, 0
        first, stop = self.cell_rows(rows)
        return _full_width(self.cells, self.cx, self.width, first, stop), first

    def cell_rows(self, rows: slice) -> tuple[int, int]:
        """[first, stop): the cell rows that frame rows ``rows`` (a non-empty slice) lie between."""
        return int(self.top[rows.start]), min(int(self.top[rows.stop - 1]) + 1, self.cells[0].shape[1] - 1) + 1


def interpolation(ch: Chroma, coarse: bool = False, whole: bool = False) -> Interpolation:
    """The :class:`Interpolation` of a chroma's shares and, with ``coarse``, its coarse luminance; ``whole``: its
    :attr:`~Interpolation.rows` made now, for several passes over the frame (else each pass's pieces make the
    cell rows they read, :meth:`~Interpolation.piece_rows`)."""
    inter = Interpolation((ch.shares, ch.coarse) if coarse else (ch.shares,), ch.layout.cell[1], ch.shape[1],
                          *_row_tables(ch.shape[0], ch.shares.shape[1], ch.layout.cell[0]))
    if whole:
        inter.rows  # noqa: B018 (made and kept)
    return inter


def _full_width(planes: tuple[np.ndarray, ...], cx: int, w: int, first: int = 0, stop: int | None = None) -> np.ndarray:
    """Cell planes (P, Hc, Wc), given as stacks of them that add up to P, interpolated bilinearly
    along rows from the cells' centres to every column, float32 (P, stop - first, W) on the cell rows
    ``first`` to ``stop`` (every one by default): as OpenCV's linear resize (which puts cell j at column
    j cx + (cx - 1) / 2)."""
    hc, wc = planes[0].shape[1:]
    stop = hc if stop is None else stop
    p = sum(stack.shape[0] for stack in planes)
    if cx in (2, 4):  # OpenCV's own arithmetic, in one pass without its row buffers, and no stacking copy
        rows = np.empty((p, stop - first, wc * cx), np.float32)
        done = 0
        for stack in planes:
            _widen(np.ascontiguousarray(stack), first, cx, rows[done:done + stack.shape[0]])
            done += stack.shape[0]
    else:
        stacked = np.ascontiguousarray(np.concatenate([stack[:, first:stop] for stack in planes]))
        rows = cv2.resize(stacked.reshape(p * (stop - first), wc), (wc * cx, p * (stop - first)),
                          interpolation=cv2.INTER_LINEAR).reshape(p, stop - first, wc * cx)
    return rows[:, :, :w]


@kernel
def _widen(planes, first, cx, out):
    """out (P, N, cx Wc) = rows ``first`` to ``first`` + N of ``planes`` (P, Hc, Wc) float32 interpolated
    linearly along rows, cell j at column j cx + (cx - 1) / 2, the ends held (cx 2 or 4): bit for bit
    OpenCV's INTER_LINEAR resize, each value a + (b - a) f with one rounding of the product and sum,
    f = (k + 1/2) / cx."""
    wc = planes.shape[2]
    c0 = cx // 2  # the first column past cell 0's centre
    for k in range(out.shape[0]):
        for i in range(out.shape[1]):
            p, o = planes[k, first + i], out[k, i]
            for x in range(c0):
                o[x] = p[0]
            if cx == 2:
                q, t = np.float32(0.25), np.float32(0.75)
                for j in range(wc - 1):
                    a = p[j]
                    d = p[j + 1] - a
                    o[2 * j + 1] = fma32(d, q, a)
                    o[2 * j + 2] = fma32(d, t, a)
            else:
                f0, f1, f2, f3 = np.float32(0.125), np.float32(0.375), np.float32(0.625), np.float32(0.875)
                for j in range(wc - 1):
                    a = p[j]
                    d = p[j + 1] - a
                    o[4 * j + 2] = fma32(d, f0, a)
                    o[4 * j + 3] = fma32(d, f1, a)
                    o[4 * j + 4] = fma32(d, f2, a)
                    o[4 * j + 5] = fma32(d, f3, a)
            for x in range(cx * (wc - 1) + c0, o.size):
                o[x] = p[wc - 1]


@lru_cache(maxsize=16)
def _row_tables(h: int, hc: int, cy: int) -> tuple[np.ndarray, np.ndarray]:
    """(top, frac) of :class:`Interpolation` for frames of ``h`` rows, cells of ``cy`` rows, read-only."""
    u = (np.arange(h) - (cy - 1) / 2) / cy
    top = np.floor(u)
    frac = (u - top).astype(np.float32)
    frac[(top < 0) | (top >= hc - 1)] = 0
    top = np.clip(top, 0, hc - 1).astype(np.intp)
    for array in (top, frac):
        array.setflags(write=False)
    return top, frac


#: Rows per piece of the per-pixel passes when they are spread over threads.
PIECE_ROWS = 128


def _pieces(h: int, align: int = 1) -> list[slice]:
    """Row ranges of about PIECE_ROWS rows (multiples of ``align``) covering ``h`` rows."""
    step = max(PIECE_ROWS // align, 1) * align
    return [slice(r, min(r + step, h)) for r in range(0, h, step)]
