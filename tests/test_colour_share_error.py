"""The detail step of colour streams: a variance of the own readings' share error (issue 26).

A colour pixel's own reading is s / (e k), k its cell's share of its channel; colour within the cells
makes that reading biased, and frames do not average the bias. The stream gives the fusion the share's
relative variance (svelive.reconstruction.stream.share_error), which the detail step adds to the fused own
reading's noise variance; that noise variance is the running mean of each frame's (e' changes with the
shares from frame to frame: TemporalState.own_variance). Monochrome frames have neither.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from svelive import Pattern
from svelive.core.camera import COLOUR_LAYOUTS
from svelive.core.cfa import ColourFilter
from svelive.reconstruction.colour import cell_layout
from svelive.reconstruction.config import MotionConfig
from svelive.reconstruction.fusion import FrameEstimate, ShareError, fuse
from svelive.reconstruction.stream import share_error, share_error_cells


def layout_of(name: str):
    pattern, cfa = COLOUR_LAYOUTS[name]
    return cell_layout(Pattern.parse(pattern), ColourFilter.parse(cfa))


def test_share_error_is_zero_for_one_colour_and_the_spread_of_the_pixels_channel_across_cells():
    layout = layout_of("dual-iso")
    cy, cx = layout.cell
    hc, wc = 6, 8
    shape = (hc * cy, wc * cx)
    shares = np.ones((3, hc, wc), np.float32)
    assert not share_error(shares, layout, shape).any()
    shares[0, :, wc // 2:] = 2.0  # red doubles from the middle column of cells on; green and blue do not change
    error = share_error(shares, layout, shape)
    channels = np.tile(layout.channels, (hc, wc))
    near = np.zeros(shape, bool)
    near[:, (wc // 2 - 1) * cx:(wc // 2 + 1) * cx] = True  # the cells beside the change
    assert np.all(error[near & (channels == 0)] > 0.05)
    assert not error[~near].any() and not error[channels != 0].any()
    # left of the change a red pixel's neighbours read twice its share: (2 - 1)^2 over half the weight
    np.testing.assert_allclose(error[0, (wc // 2 - 1) * cx:wc // 2 * cx][layout.channels[0] == 0], 0.25, rtol=1e-6)


def frames(bias: float, n: int = 8, shape=(24, 24), seed: int = 0):
    """Frames of a flat scene of 100 DN whose estimate is right, but whose own readings on every other
    column read ``bias`` too high (a share too small there); per-pixel exposures (a colour frame's e')."""
    rng = np.random.default_rng(seed)
    exposure = np.full(shape, 4.0, np.float32)
    exposure[:, 1::2] *= 2
    truth = np.full(shape, 100.0, np.float32)
    reading = truth * np.where(np.arange(shape[1]) % 2 == 1, 1 + bias, 1).astype(np.float32)
    out = []
    for _ in range(n):
        signal = (reading * exposure + rng.normal(0, 0.5, shape)).astype(np.float32)
        image = (truth + rng.normal(0, 0.05, shape)).astype(np.float32)
        no = np.zeros(shape, bool)
        out.append(FrameEstimate(image, np.full(shape, 0.01, np.float32), no, no, signal, None,
                                 np.float32(0.01), np.float32(0.25), exposure=exposure))
    return out


def run(stream, error=None):
    state, result = None, None
    for frame in stream:
        if error is not None:
            frame = FrameEstimate(*(getattr(frame, f) for f in ("image", "variance", "bound", "censored", "signal",
                                                               "inverse", "own_slope", "own_floor")),
                                  share_error=np.full(frame.image.shape, error, np.float32), exposure=frame.exposure)
        result = fuse(state, frame, MotionConfig(), (2, 1))
        state = result.state
    return result


def test_a_reading_over_a_small_share_in_one_frame_is_not_taken_in_the_next():
    """A pixel beside a moving object's colour reads over a tiny share in one frame (its e' = e k then
    tiny, its own reading that much noisier) and over its own share in the next: the fused own reading
    carries the first frame's noise, which the history's own variance keeps (without it, the detail
    step took that reading: the trail of a bright coloured disc on a dark ground, quad-bayer)."""
    first, second = frames(0.0, n=2)
    patch = (slice(8, 16), slice(8, 16))
    exposure = first.exposure.copy()
    exposure[patch] /= 1000  # a share of 1/1000
    signal = first.signal.copy()
    signal[patch] = signal[patch] / 1000 + np.random.default_rng(1).normal(0, 0.5, (8, 8)).astype(np.float32)
    first = FrameEstimate(first.image, first.variance, first.bound, first.censored, signal, None,
                          first.own_slope, first.own_floor, exposure=exposure)
    stream = [first, second]
    old = run(stream).image[patch]
    assert np.abs(old - 100).mean() > 20  # the first frame's reading, its noise 250x the second's: taken
    tracked = run(stream, 0.0)
    assert np.abs(tracked.image[patch] - 100).mean() < 0.5  # within that noise: the estimate stays
    assert tracked.state.own_variance[patch].min() > 1000 * tracked.state.own_variance[0, 0]


def test_the_detail_step_does_not_chase_a_bias_within_the_share_error():
    biased = np.arange(24) % 2 == 1
    without = run(frames(0.2)).image[:, biased]
    assert np.mean(without) > 115  # the detail step takes the biased own readings
    within = run(frames(0.2), 0.2 ** 2).image[:, biased]
    assert abs(np.mean(within) - 100) < 3  # their bias is within the share's error: the estimate stays


@pytest.mark.parametrize("name", ["dual-iso", "quad-bayer"])
def test_the_fusion_reads_the_share_error_by_cell_as_its_plane_bit_for_bit(name):
    """The stream gives the fusion its share error by cell (no plane written and read): the same fusion as with
    the plane, strip by strip (strips of one cell row; a width that cuts the last cells). The error lies around two
    cells only, so that the output shows where it is: the plane moved by one row gives another."""
    layout = layout_of(name)
    cy, cx = layout.cell
    shape = (6 * cy, 5 * cx - 1)
    shares = np.ones((3, 6, 5), np.float32)
    shares[:, 2, 2], shares[0, 4, 1] = 3.0, 0.3
    cells = share_error_cells(shares, layout)
    assert isinstance(cells, ShareError)
    plane = share_error(shares, layout, shape)
    results = []
    for error in (plane, cells, np.roll(plane, 1, axis=0)):
        state = None
        for frame in frames(0.2, n=4, shape=shape):
            result = fuse(state, replace(frame, share_error=error), MotionConfig(), (2, 1), strip_rows=cy)
            state = result.state
        results.append(result.image)
    np.testing.assert_array_equal(results[0], results[1])
    assert not np.array_equal(results[0], results[2])


def test_a_frame_takes_tables_or_per_pixel_exposures():
    frame = frames(0.0, n=1)[0]
    with pytest.raises(ValueError):  # numbers for the variance need the exposures they scale
        FrameEstimate(frame.image, frame.variance, frame.bound, frame.censored, frame.signal,
                      1 / frame.exposure, frame.own_slope, frame.own_floor)


@pytest.mark.parametrize("hc", [1, 2, 3, 17])
def test_the_spread_made_again_on_the_changed_cell_rows_is_the_whole_spread(hc):
    """share_error_cells with the spread of the last shares (``cells``) and the cell rows that changed since: the
    spread of the new shares, bit for bit, made again in place only where a cell row's 3x3 reads a changed one
    (the others keep their values: a marker there stays); changes at the edges, next to each other, one, none."""
    layout = layout_of("dual-iso")
    rng = np.random.default_rng(7)
    wc = 9
    before = rng.uniform(0.2, 2.0, (3, hc, wc)).astype(np.float32)
    for changes in ([], [0], [hc - 1], [hc // 2], [0, hc - 1], list(range(hc))):
        changed = np.zeros(hc, bool)
        changed[changes] = True
        after = before.copy()
        after[:, changed] = rng.uniform(0.2, 2.0, (3, np.count_nonzero(changed), wc)).astype(np.float32)
        cells = share_error_cells(before, layout).cells
        reads = changed | np.r_[changed[1:], False] | np.r_[False, changed[:-1]]
        cells[:, ~reads] = -1.0  # (kept, not made again: the marker stays)
        got = share_error_cells(after, layout, cells, changed)
        assert got.cells is cells
        whole = share_error_cells(after, layout).cells
        np.testing.assert_array_equal(cells[:, reads], whole[:, reads])
        assert np.all(cells[:, ~reads] == -1.0)
        if hc > 1 and changes == [hc // 2]:
            assert np.count_nonzero(reads) == min(3, hc)
