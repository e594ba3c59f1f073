"""A colour stream's passes at cell resolution in strips of cell rows over threads (colour.cell_strips,
base.map_on): the share error and the fused chroma's cell weights give the one thread's result bit for bit,
down to strips of one cell row."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from svelive import Pattern
from svelive.core.camera import COLOUR_LAYOUTS
from svelive.core.cfa import ColourFilter
from svelive.reconstruction.colour import Chroma, cell_layout, cells
from svelive.reconstruction.stream import fuse_chroma, share_error


@pytest.mark.parametrize("layout_name", ["dual-iso", "quad-bayer"])
@pytest.mark.parametrize("strips_per_thread", [1, 3, 1000])
def test_share_error_and_fused_chroma_in_strips_are_one_threads(layout_name, strips_per_thread, monkeypatch):
    pattern, cfa = COLOUR_LAYOUTS[layout_name]
    layout = cell_layout(Pattern.parse(pattern), ColourFilter.parse(cfa))
    cy, cx = layout.cell
    rng = np.random.default_rng(strips_per_thread)
    hc, wc = 13, 9
    shape = (hc * cy - 1, wc * cx)  # (the last cell row short of a whole cell)
    shares = rng.uniform(0.2, 2.0, (3, hc, wc)).astype(np.float32)
    coarse = rng.uniform(0, 100, (2, hc, wc)).astype(np.float32)
    history = rng.uniform(0, 2, (5, hc, wc)).astype(np.float32)
    weight = rng.choice(np.array([1.0, 0.5, 0.25, 0.125], np.float32), shape)
    chroma = Chroma(shares, coarse, layout, np.ones(3, np.float32), shape)
    error, fused = share_error(shares, layout, shape), fuse_chroma(history, chroma, weight, 0.9)
    monkeypatch.setattr(cells, "STRIPS_PER_THREAD", strips_per_thread)
    assert len(cells.cell_strips(hc, 2)) == min(2 * strips_per_thread, hc)
    with ThreadPoolExecutor(2) as pool:
        for workers in (2, pool):
            np.testing.assert_array_equal(share_error(shares, layout, shape, workers), error)
            np.testing.assert_array_equal(fuse_chroma(history, chroma, weight, 0.9, workers), fused)
