"""A colour stream's passes at cell resolution spread over threads in strips of cell rows (issue 25: the live
colour stream's serial stretches): the share error, the chroma's fusion and the shares' interpolation give the
same values, bit for bit, in strips of any height, on the caller's thread or over two threads, as in one
piece."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from svelive import Camera, Pattern, Sensor, simulate
from svelive.core.camera import COLOUR_LAYOUTS
from svelive.reconstruction.colour import cells, chroma, interpolate, interpolation
from svelive.reconstruction.input import prepare
from svelive.reconstruction.stream import fuse_chroma, share_error
from svelive.simulation import exposure_scale, load_sample_scene

SENSOR = Sensor.from_full_well(12, 10_000, 3)


def _chroma(layout: str, seed: int):
    pattern, cfa = COLOUR_LAYOUTS[layout]
    rgb = np.maximum(load_sample_scene("desk", rgb=True), 0)[:150, 30:130]
    scale = np.float32(exposure_scale(rgb, Pattern.parse(pattern), SENSOR, stops_below_fill=1))
    inp = prepare(simulate(rgb * scale, pattern, SENSOR, cfa=cfa, seed=seed).raw, Camera.build(pattern, cfa, SENSOR))
    return chroma(inp)


def _outputs(workers) -> list[np.ndarray]:
    out = []
    for layout in ("dual-iso", "quad-bayer"):
        this, last = _chroma(layout, 1), _chroma(layout, 2)
        history = np.concatenate([last.shares, last.coarse])
        weight = np.random.default_rng(0).choice(np.float32([1, 0.5, 0.25, 0.125]), this.shape).astype(np.float32)
        out.append(share_error(this.shares, this.layout, this.shape, workers))
        out.append(fuse_chroma(history, this, weight, 1.25, workers))
        inter = interpolation(this, coarse=True, workers=workers)
        out.append(inter.rows)
    return out


@pytest.mark.parametrize("strip", [1, 3, 7])
def test_strips_of_any_height_over_threads_give_the_one_piece_values(monkeypatch, strip):
    monkeypatch.setattr(cells, "STRIP_CELL_ROWS", 10_000)
    monkeypatch.setattr(interpolate, "PIECE_ROWS", 10_000)
    whole = _outputs(1)
    monkeypatch.setattr(cells, "STRIP_CELL_ROWS", strip)
    monkeypatch.setattr(interpolate, "PIECE_ROWS", strip * 4)
    assert len(cells.cell_strips(whole[1].shape[1])) > 2
    with ThreadPoolExecutor(2) as pool:
        for workers in (1, pool):
            for got, expected in zip(_outputs(workers), whole):
                np.testing.assert_array_equal(got, expected)
