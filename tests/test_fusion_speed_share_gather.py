"""The share error's gather (svelive.reconstruction.fusion._share_gather): each pixel takes its channel's
value of its cell, whichever loop writes it (cells two columns wide take one of their own)."""

from __future__ import annotations

import numpy as np
import pytest

from svelive.reconstruction.fusion import _share_gather


@pytest.mark.parametrize("channels", [[[0, 1], [1, 2]], [[0, 1], [1, 2], [0, 1], [1, 2]], [[0, 1, 2]], [[2]]])
@pytest.mark.parametrize("width", [1, 5, 6, 13])
def test_gather_gives_each_pixel_its_channels_cell(channels: list[list[int]], width: int) -> None:
    channels = np.array(channels, np.uint8)
    cy, cx = channels.shape
    height = 3 * cy + 1
    cells = np.random.default_rng(width).random((3, -(-height // cy), -(-width // cx)), dtype=np.float32)
    out = np.empty((height, width), np.float32)
    _share_gather(cells, channels, out)
    rows, cols = np.indices((height, width))
    expected = cells[channels[rows % cy, cols % cx], rows // cy, cols // cx]
    np.testing.assert_array_equal(out, expected)
