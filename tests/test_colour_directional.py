"""Directional demosaicing of the joint colour's site values (svelive.reconstruction.colour.directional):
Menon et al.'s algorithm against colour-demosaicing's implementation (the test extra), its
properties, and the stage (opt-in ``joint(..., directional=True)``): own channels kept,
luminance consistent, clipped neighbourhoods, tiles without colour texture and non-Bayer CFAs untouched."""

from __future__ import annotations

import numpy as np
import pytest

from svelive.bench.stability import BENCH_SENSOR, _simulated_rgb
from svelive.core.camera import Camera
from svelive.reconstruction.colour import joint
from svelive.reconstruction.colour.directional import (MARGIN, PARITY, TILE, Grid, demosaic_log, directional_channels,
                                                       log_floor)
from svelive.reconstruction.input import prepare
from svelive.reconstruction.methods import METHODS

#: Bayer pattern name -> (row, column) of red.
PATTERNS = {"RGGB": (0, 0), "BGGR": (1, 1), "GRBG": (0, 1), "GBRG": (1, 0)}


def _mosaics(shape=(24, 32)) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(1)
    yy, xx = np.mgrid[:shape[0], :shape[1]].astype(np.float32)
    structured = np.sin(0.7 * xx + 0.2 * yy) + 0.3 * (xx > 15) + 0.5 * (yy % 7 == 0)
    return {"random": rng.random(shape).astype(np.float32), "structured": structured.astype(np.float32)}


def _own(rgb: np.ndarray, red: tuple[int, int]) -> np.ndarray:
    h, w = rgb.shape[:2]
    rr = (np.arange(h) % 2 == red[0])[:, None]
    rc = (np.arange(w) % 2 == red[1])[None, :]
    ch = np.where(rr & rc, 0, np.where(~rr & ~rc, 2, 1))
    return np.take_along_axis(rgb, ch[..., None], axis=2)[..., 0]


@pytest.mark.parametrize("pattern", sorted(PATTERNS))
@pytest.mark.parametrize("refine", [False, True])
def test_matches_colour_demosaicing(pattern, refine):
    """The same algorithm as colour-demosaicing's demosaicing_CFA_Bayer_Menon2007 (borders included)."""
    import colour_demosaicing  # the test extra's reference implementation
    for name, mosaic in _mosaics().items():
        theirs = colour_demosaicing.demosaicing_CFA_Bayer_Menon2007(mosaic.astype(np.float64), pattern,
                                                                     refining_step=refine)
        mine = demosaic_log(mosaic, PATTERNS[pattern], refine)
        np.testing.assert_allclose(mine, theirs, atol=1e-4, err_msg=name)


@pytest.mark.parametrize("pattern", sorted(PATTERNS))
def test_properties(pattern):
    """Own channel kept, finite output, a flat colour stays flat."""
    red = PATTERNS[pattern]
    for mosaic in _mosaics().values():
        out = demosaic_log(mosaic, red)
        assert np.all(np.isfinite(out))
        np.testing.assert_array_equal(_own(out, red), mosaic)
    flat = np.array([1.5, -0.25, 3.0], np.float32)
    mosaic = _own(np.broadcast_to(flat, (16, 20, 3)).copy(), red)
    np.testing.assert_allclose(demosaic_log(mosaic, red), np.broadcast_to(flat, (16, 20, 3)), atol=1e-5)


@pytest.mark.parametrize("vertical", [True, False])
def test_edges_interpolated_along_the_edge(vertical):
    """A grey step (all channels equal on each side): every missing channel takes its own side's value,
    as interpolation along the edge gives (across it, the two sides would be mixed)."""
    shape = (20, 24)
    yy, xx = np.mgrid[:shape[0], :shape[1]]
    grey = np.where((xx if vertical else yy) < 11, 0.0, 4.0).astype(np.float32)
    out = demosaic_log(grey, (0, 0))
    np.testing.assert_allclose(out[3:-3, 3:-3], np.repeat(grey[3:-3, 3:-3, None], 3, axis=2), atol=1e-5)


def _frame(layout: str, seed: int = 4, shape: tuple[int, int] = (64, 96), light: float = 40.0,
           size: int = 3) -> tuple:
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:shape[0], :shape[1]].astype(np.float32)
    base = 1.0 + 0.8 * np.sin(0.35 * xx + 0.1 * yy)
    tint = np.stack([1.0 + 0.5 * (xx > 40), np.ones(shape), 1.2 - 0.4 * (yy > 30)], axis=-1)
    full = BENCH_SENSOR.censor_level / float(Camera.build(layout, sensor=BENCH_SENSOR).require_pattern().levels[0])
    truth = (base[..., None] * tint * rng.uniform(0.9, 1.1, (1, 1, 3)) * 0.02 * full).astype(np.float32)
    truth[10:10 + size, 10:10 + size] *= light  # a clipped light (in the long readings; over 400: the short too)
    return prepare(_simulated_rgb(truth, layout, seed), Camera.build(layout, sensor=BENCH_SENSOR))


def _clipped(inp) -> np.ndarray:
    """The censored readings with no uncensored reading of their own channel in their 5x5 (OpenCV's dilation)."""
    import cv2

    out = np.zeros_like(inp.censored)
    for c in range(3):
        own = inp.channels == c
        measured = (own & ~inp.censored).view(np.uint8)
        near = cv2.dilate(measured, np.ones((5, 5), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)
        out |= own & inp.censored & ~near.view(bool)
    return out


def test_stage_keeps_own_channels_and_luminance():
    inp = _frame("dual-iso", light=1000.0, size=9)
    spec = METHODS["adaptive"]
    before = joint(inp, spec).estimate
    after = joint(inp, spec, directional=True).estimate
    ch = inp.channels.astype(np.intp)[..., None]
    np.testing.assert_array_equal(np.take_along_axis(after.image, ch, 2), np.take_along_axis(before.image, ch, 2))
    assert np.all(np.isfinite(after.image)) and np.all(after.image >= 0)
    changed = np.any(after.image != before.image, axis=2)
    assert changed.mean() > 0.5
    share = joint(inp, spec).chroma.layout.share
    np.testing.assert_allclose(after.luminance[changed], after.image[changed] @ share, rtol=1e-5)
    np.testing.assert_array_equal(after.luminance[~changed], before.luminance[~changed])
    # within a pixel of a clipped reading, nothing changes (the highlight rules stay)
    gate = _clipped(inp)
    assert gate.any()
    near = np.zeros_like(gate)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            near |= np.roll(np.roll(gate, dy, 0), dx, 1)
    assert not changed[near].any()


def test_stage_leaves_other_cfas():
    inp = _frame("quad-bayer")
    spec = METHODS["adaptive"]
    np.testing.assert_array_equal(joint(inp, spec, directional=True).estimate.image, joint(inp, spec).estimate.image)


@pytest.mark.parametrize("pattern", sorted(PATTERNS))
def test_matches_colour_demosaicing_odd_sizes(pattern):
    """Odd heights and widths (the quarter planes' padding then covers a missing last row or column)."""
    import colour_demosaicing
    mosaic = _mosaics((25, 31))["random"]
    theirs = colour_demosaicing.demosaicing_CFA_Bayer_Menon2007(mosaic.astype(np.float64), pattern)
    np.testing.assert_allclose(demosaic_log(mosaic, PATTERNS[pattern]), theirs, atol=1e-4)


@pytest.mark.parametrize("shape", [(8, 10), (9, 7)])
@pytest.mark.parametrize("pattern", sorted(PATTERNS))
def test_grid_planes_mirror_the_frame(shape, pattern):
    """Grid.split: each quarter plane holds its parity's pixels of the frame padded by mirroring about the
    edge pixels (cv2.BORDER_REFLECT_101), red at even rows and columns of the padded frame."""
    import cv2

    red = PATTERNS[pattern]
    frame = np.random.default_rng(2).random(shape).astype(np.float32)
    grid = Grid(shape, red)
    planes = grid.planes(4)
    grid.split(frame, planes)
    bottom, right = 2 * grid.hq - grid.top - shape[0], 2 * grid.wq - grid.left - shape[1]
    # (the padding is at most 4 deep: within reach of a single reflection for these sizes)
    padded = cv2.copyMakeBorder(frame, grid.top, bottom, grid.left, right, cv2.BORDER_REFLECT_101)
    for kind, (py, px) in enumerate(PARITY):
        np.testing.assert_array_equal(planes[kind], padded[py::2, px::2])
    assert padded[grid.top + red[0], grid.left + red[1]] == frame[red] and (grid.top + red[0]) % 2 == 0
    assert (grid.left + red[1]) % 2 == 0


def test_stage_independent_of_workers():
    inp = _frame("dual-iso", seed=5, shape=(300, 96))  # several pieces of rows (of the frame and of the planes)
    spec = METHODS["adaptive"]
    base = joint(inp, spec)
    images = []
    for workers in (1, 3):
        image, luminance = base.estimate.image.copy(), base.estimate.luminance.copy()
        assert directional_channels(inp, luminance, image, base.chroma.layout.share,
                                    log_floor(inp, base.chroma.layout), workers=workers)
        images.append((image, luminance))
    np.testing.assert_array_equal(images[0][0], images[1][0])
    np.testing.assert_array_equal(images[0][1], images[1][1])


def test_weights_match_opencv_windows():
    """_block's rings of rows against the windows done with OpenCV: the lattice blend of the 3x3's smallest
    share (edge replicated) times the 5x5 mean of m^2 / (m^2 + v) (cv2.BORDER_REFLECT), 0 within a pixel of a
    clipped reading; the planes get ln(max(m, 0) + floor) of each site; and the colour texture by row and tile."""
    import cv2

    from svelive.reconstruction.colour.directional import _block, _texture_rows, red_site
    from svelive.reconstruction.colour.lattice import F_HIGH, F_LOW

    inp = _frame("dual-iso", seed=6, shape=(150, 70))
    j = joint(inp, METHODS["adaptive"])
    rgb, floor = j.estimate.image, np.float32(log_floor(inp, j.chroma.layout))
    own = np.take_along_axis(rgb, inp.channels.astype(np.intp)[..., None], 2)[..., 0]
    top = rgb.max(axis=2)
    share = np.where(top > 0, own / np.where(top > 0, top, 1), 1).astype(np.float32)
    e, level = inp.exposure.astype(np.float32), np.maximum(own, 0)
    variance = (e * level / inp.sensor.effective_gain + inp.sensor.floor_variance) / (e * e)
    snr = np.where(inp.censored, 0, level ** 2 / (level ** 2 + variance)).astype(np.float32)  # (a fill: 0)
    smallest = cv2.erode(share, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)
    expected = np.clip((smallest - F_LOW) / (F_HIGH - F_LOW), 0, 1) * cv2.blur(snr, (5, 5), borderType=cv2.BORDER_REFLECT)
    gate = _clipped(inp)
    assert (gate != inp.censored).any()  # (censored long readings beside uncensored short ones of their channel)
    expected[cv2.dilate(gate.view(np.uint8), np.ones((3, 3), np.uint8)).view(bool)] = 0
    grid = Grid(inp.shape, red_site(inp))
    # the colour texture: 2 |U - M| / (U + M) (U the value of the neighbours' channel, M their readings' mean, both
    # plus the floor), 0 at the rows' ends, summed by row over each tile's frame columns
    across = np.take_along_axis(rgb, np.roll(inp.channels, 1, axis=1).astype(np.intp)[..., None], 2)[..., 0]
    u, mid = np.maximum(across, 0) + floor, 0.5 * (np.roll(level, 1, 1) + np.roll(level, -1, 1)) + floor
    texture = 2 * np.abs(u - mid) / (u + mid)
    texture[:, [0, -1]] = 0
    tiles = (np.arange(inp.shape[1]) + grid.left) // 2 // TILE
    sums = np.stack([texture[:, tiles == t].sum(axis=1) for t in range(tiles.max() + 1)], axis=1)
    activity = np.empty((inp.shape[0], sums.shape[1]), np.float32)
    _texture_rows(rgb, floor, grid.top, grid.left, activity, 0, inp.shape[0])
    np.testing.assert_allclose(activity, sums, rtol=1e-5, atol=1e-5)
    planes, weight, corner = _block(inp, rgb, inp.exposure.astype(np.float32), grid, floor, (0, grid.hq),
                                    (1, grid.wq - 1))
    assert corner == (0, 0)
    np.testing.assert_allclose(weight, expected, atol=1e-6)
    logs = grid.planes(4)
    grid.split(np.log(level + floor).astype(np.float32), logs)
    np.testing.assert_allclose(planes, logs, rtol=1e-6, atol=1e-6)
    # a block's weight is the frame's more than 3 pixels inside its edges
    rows, columns = (10, 40), (9, 25)
    _, part, (y0, x0) = _block(inp, rgb, inp.exposure.astype(np.float32), grid, floor, rows, columns)
    inner = (slice(y0 + 3, y0 + part.shape[0] - 3), slice(x0 + 3, x0 + part.shape[1] - 3))
    np.testing.assert_array_equal(part[3:-3, 3:-3], weight[inner])


@pytest.mark.parametrize("pattern", sorted(PATTERNS))
def test_streamed_rows_independent_of_chunks_and_pieces(pattern):
    """The streamed demosaicing (_stream) gives every plane row the same values whatever the size of its
    output ring (the chunks the stage exponentiates and blends) and whichever rows a run covers (the
    stage's pieces on several threads, each recomputing the steps' reach beyond its rows)."""
    from svelive.reconstruction.colour.directional import _stream

    frame = np.random.default_rng(3).random((37, 29)).astype(np.float32)
    grid = Grid(frame.shape, PATTERNS[pattern])
    planes = grid.planes(4)
    grid.split(frame, planes)
    rows = slice(1, grid.hq - 1)
    whole = np.full((grid.hq, 8, grid.wq), np.nan, np.float32)
    _stream(grid, planes, True, 1, grid.hq - 1, whole, lambda a, b: None)
    assert np.all(np.isfinite(whole[rows, :, 1:-1]))
    for size in (1, 3, 8):
        ring = np.empty((size, 8, grid.wq), np.float32)
        got = np.full_like(whole, np.nan)

        def chunk(a: int, b: int) -> None:
            assert b - a <= size and (a % size) + (b - a) <= size  # a chunk never wraps the ring
            got[a:b] = ring[a % size:(b - 1) % size + 1]

        for first, last in ((1, 5), (5, 6), (6, grid.hq - 1)):
            _stream(grid, planes, True, first, last, ring, chunk)
        np.testing.assert_array_equal(got[rows, :, 1:-1], whole[rows, :, 1:-1])


@pytest.mark.parametrize("pattern", sorted(PATTERNS))
def test_streamed_columns_match_the_whole_frame(pattern):
    """_stream on a block of plane columns (c0, c1) gives the whole frame's values at its columns more than
    MARGIN inside an edge of the block that is not the frame's (its ``out`` column j: the planes' c0 - 1 + j)."""
    from svelive.reconstruction.colour.directional import _stream

    frame = np.random.default_rng(7).random((41, 170)).astype(np.float32)
    grid = Grid(frame.shape, PATTERNS[pattern])
    planes = grid.planes(4)
    grid.split(frame, planes)
    whole = np.empty((grid.hq, 8, grid.wq), np.float32)
    _stream(grid, planes, True, 1, grid.hq - 1, whole, lambda a, b: None)
    rows = slice(3, 15)
    for c0, c1, inside in ((30, 64, slice(30 + MARGIN, 64 - MARGIN)), (1, 40, slice(1, 40 - MARGIN)),
                           (50, grid.wq - 1, slice(50 + MARGIN, grid.wq - 1))):
        width = c1 - c0 + 2
        block = np.empty((grid.hq, 8, width), np.float32)
        _stream(grid, np.ascontiguousarray(planes[:, :, c0 - 1:c1 + 1]), True, rows.start, rows.stop, block,
                lambda a, b: None, (c0, c1))
        got = block[rows, :, inside.start - c0 + 1:inside.stop - c0 + 1]
        np.testing.assert_array_equal(got, whole[rows, :, inside])


def test_stage_only_on_tiles_with_colour_texture():
    """With the texture test, the stage's result is the whole frame's (texture None) in the tiles it runs on
    and the input elsewhere; a frame of one colour gets no tile."""
    from svelive.reconstruction.colour.directional import _spans, _texture_rows, red_site

    inp = _frame("dual-iso", seed=8, shape=(200, 160))
    j = joint(inp, METHODS["adaptive"])
    share, floor = j.chroma.layout.share, log_floor(inp, j.chroma.layout)
    results = {}
    for texture in (None, 0.03):
        image, luminance = j.estimate.image.copy(), j.estimate.luminance.copy()
        directional_channels(inp, luminance, image, share, floor, texture=texture)
        results[texture] = image
    grid = Grid(inp.shape, red_site(inp))
    activity = np.empty((inp.shape[0], (grid.left + inp.shape[1]) // 2 // TILE + 1), np.float32)
    _texture_rows(j.estimate.image, np.float32(floor), grid.top, grid.left, activity, 0, inp.shape[0])
    spans = _spans(grid, activity, 0.03)
    assert 0 < len(spans) < len(_spans(grid, activity, None)) * (grid.wq // TILE)
    run = np.zeros(inp.shape, bool)
    for first, last, j0, j1 in spans:
        run[max(2 * first - grid.top, 0):2 * last - grid.top, max(2 * j0 - grid.left, 0):2 * j1 - grid.left] = True
    np.testing.assert_array_equal(results[0.03][run], results[None][run])
    np.testing.assert_array_equal(results[0.03][~run], j.estimate.image[~run])
    assert (results[0.03] != j.estimate.image).any() and run.mean() < 1
    flat = j.estimate.image.copy()
    flat[:] = flat.reshape(-1, 3).mean(axis=0)
    _texture_rows(flat, np.float32(floor), grid.top, grid.left, activity, 0, inp.shape[0])
    assert _spans(grid, activity, 0.03) == []
