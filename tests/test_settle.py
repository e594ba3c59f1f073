"""The band refresh of issue 25 (svelive.reconstruction.settle): ``adaptive`` on bands, cells and edge stacks gives the
full frame's results bit for bit; ``refresh=K`` streams skip bands and stay close to the stream without it."""

from concurrent.futures import ThreadPoolExecutor

import numpy as np

from svelive.capture.demo import DemoSource
from svelive.reconstruction import Reconstructor, settle
from svelive.reconstruction.input import prepare
from svelive.reconstruction.methods.adaptive import _estimate, noise_model


def _frames(n, width=328, height=200):
    demo = DemoSource("demo", width=width, height=height, fps=0, period_s=1e9, cfa="none")
    try:
        return list(demo.frames(limit=n))
    finally:
        demo.close()


def _dimmed_input(frame, dim):
    """The frame's SveInput with its readings above black times ``dim`` (1: as it is)."""
    raw = frame.raw
    if dim != 1.0:
        black = frame.camera.sensor.black_level
        raw = (np.round((raw.astype(np.float32) - black) * dim) + black).astype(raw.dtype)
    return prepare(raw, frame.camera)


def _needed(h, w, seed):
    """bool (h, w): 40 random pixels, the corners and pixels by every edge: where an on-demand estimate is asked."""
    rng = np.random.default_rng(seed)
    need = np.zeros((h, w), bool)
    need[rng.integers(0, h, 40), rng.integers(0, w, 40)] = True
    for y, x in [(0, 0), (0, w - 1), (h - 1, 0), (h - 1, w - 1), (3, 100), (h - 2, 50), (90, 1), (91, w - 1)]:
        need[y, x] = True
    return need


def _assert_on_demand_is_the_full_frames(part, need, full, workers=1):
    """settle.on_demand at ``need``'s pixels gives the full frame's (image, lower, variance) there, bit for bit."""
    ys, xs, values, _ = settle.on_demand(part, *np.nonzero(need), workers)
    assert ys.size == np.count_nonzero(need)
    for got, want in zip(values, full):
        np.testing.assert_array_equal(got, want[ys, xs])


def test_bands_cells_and_edges_give_the_full_frames_results():
    frame = _frames(1)[0]
    for dim in (1.0, 2.0 ** -8):  # bright (censored readings), and dim (the wide fallback)
        inp = _dimmed_input(frame, dim)
        noise = noise_model(inp)
        image, lower, variance, _, _, window = _estimate(inp, noise, 1, want_variance=True, want_window=True)
        h, w = inp.shape
        bands = len(settle.bands(h))
        need = _needed(h, w, 3)
        part = settle.Partial(inp, noise, np.zeros(bands, bool), np.zeros(h, bool))
        with ThreadPoolExecutor(2) as pool:  # (the atlases and stacks as jobs over threads, or on the caller's)
            for workers in (1, 3, pool):
                _assert_on_demand_is_the_full_frames(part, need, (image, lower, variance), workers)
        selected = np.arange(bands) % 2 == 0
        out = (np.zeros((h, w), np.float32), np.zeros((h, w), bool), np.zeros((h, w), np.float32),
               np.zeros((2, h, w), np.float32))
        settle.method_on_bands(inp, noise, selected, *out)
        rows = np.repeat(selected, settle.BAND_ROWS)[:h]
        for got, want in zip(out, (image, lower, variance)):
            np.testing.assert_array_equal(got[rows], want[rows])
        np.testing.assert_array_equal(out[3][:, rows], window[:, rows])
        skipped = [(a * settle.BAND_ROWS, min(b * settle.BAND_ROWS, h)) for a, b in settle.runs(~selected)]
        settle.window_rows(inp, image, variance, skipped, out[3][0], out[3][1])
        np.testing.assert_array_equal(out[3], window)
        # the rows below the first band, in pieces over threads (the run is long enough to be cut)
        assert len(settle.pieces([(settle.BAND_ROWS, h)], 2)) > 1
        with ThreadPoolExecutor(2) as pool:
            for workers in (2, pool):
                level = np.zeros((2, h, w), np.float32)
                settle.window_rows(inp, image, variance, [(settle.BAND_ROWS, h)], level[0], level[1], None, workers)
                np.testing.assert_array_equal(level[:, settle.BAND_ROWS:], window[:, settle.BAND_ROWS:])


def test_a_refresh_stream_skips_bands_of_a_still_view_and_stays_close():
    frames = _frames(14, 328, 400)
    off, on = Reconstructor(frames[0].camera), Reconstructor(frames[0].camera, refresh=4)
    computed = []
    for f in frames:
        a, b = off.process(f), on.process(f)
        p = on.last_partial  # (None while the estimated noise model is not trusted: the method everywhere)
        computed.append(1.0 if p is None else p["computed"] / p["bands"])
        assert b.method_rows == computed[-1] and a.method_rows == 1.0  # what the live ladder's costs read
        assert np.isfinite(b.image).all() and (b.image >= 0).all()
    assert min(computed[9:]) < 0.75  # bands skipped once the history settled
    rel = np.abs(b.image - a.image) / np.maximum(a.image, 1.0)
    assert float(np.sqrt(np.mean(rel ** 2))) < 0.03


def _moving_disc_raws(n=26, shape=(320, 256)):
    """Raw uint16 frames (12-bit, black 64) of a still procedural scene across which a textured disc starts moving
    at frame 12 and stops at frame 18 (5 bands of 64 rows; the disc crosses bands 2 and 3), and their sensor."""
    from svelive import Sensor, simulate
    from svelive.bench import motion_cases as mc

    sensor = Sensor.from_full_well(12, 10_000, 3, black_level=64, white_level=4095)
    background = mc.dim(mc.procedural_scene(shape, 5), "1,4/16,64", sensor, 2.0)
    texture = mc.dim(mc.procedural_scene((64, 64), 6), "1,4/16,64", sensor, 0.5)
    scene = mc.starting(mc.stopping(mc.moving_texture(background, texture, 22.0, (150.0, 30.0), (3.0, 9.0)), 6), 12)
    return [simulate(scene(float(i)), "1,4/16,64", sensor, seed=i).raw for i in range(n)], sensor


def test_frames_estimated_ahead_fuse_as_the_sequential_stream():
    """The band selection is decided by the history a frame is fused into: a stream whose frames are estimated
    one and two frames ahead of their fusion (two threads of a live service) gives the sequential stream's
    output, motion, weights and history, bit for bit, although its estimates' hints differ."""
    from collections import deque

    raws, sensor = _moving_disc_raws()
    kw = dict(black_level=64, white_level=4095, gain=sensor.gain, read_noise=sensor.read_noise, refresh=4)
    for lag in (1, 2):
        sequential, ahead = Reconstructor("1,4/16,64", **kw), Reconstructor("1,4/16,64", **kw)
        pending, changed, skipped = deque(), 0, 0
        fused = []
        for raw in raws + [None] * lag:
            if raw is not None:
                pending.append(ahead.estimate(raw))
            if len(pending) > lag or raw is None:
                fused.append(ahead.fuse(pending.popleft()))
                p = ahead.last_partial
                changed += p["added"] + p["dropped"]
                skipped += p["bands"] - p["computed"]
                i = len(fused) - 1
                want = sequential.process(raws[i])
                got = fused[-1]
                np.testing.assert_array_equal(got.image, want.image, err_msg=f"lag {lag}, frame {i}")
                np.testing.assert_array_equal(got.motion, want.motion, err_msg=f"lag {lag}, frame {i}")
                np.testing.assert_array_equal(got.weight, want.weight, err_msg=f"lag {lag}, frame {i}")
                np.testing.assert_array_equal(got.variance_of(), want.variance_of(), err_msg=f"lag {lag}, {i}")
                assert sequential.last_partial["computed"] == p["computed"]
                for name in ("mean", "own", "weight", "bound", "censored", "test"):
                    np.testing.assert_array_equal(getattr(ahead._history, name), getattr(sequential._history, name),
                                                  err_msg=f"lag {lag}, frame {i}: history {name}")
        assert changed > 0  # the hints missed bands or took some the stream skips: the reconciliation ran
        state = ahead.refresh_state()
        assert state["hint_added"] + state["hint_dropped"] == changed
        assert sequential.refresh_state()["hint_added"] == sequential.refresh_state()["hint_dropped"] == 0
        assert skipped > 0  # and bands were skipped


def test_a_fused_frame_keeps_no_history_alive():
    """A partial frame's estimate, held after its fusion (a live service's loop holds it until its next frame),
    holds neither the history it was fused into nor a whole frame of its own beyond the estimate's: the stream's
    history alone lives on (issue 25, memory)."""
    import gc
    import weakref

    raws, sensor = _moving_disc_raws(14)
    stream = Reconstructor("1,4/16,64", black_level=64, white_level=4095, gain=sensor.gain,
                           read_noise=sensor.read_noise, refresh=4)
    checked = 0
    for raw in raws:
        before = weakref.ref(stream._history) if stream._history is not None else None
        estimated = stream.estimate(raw)
        stream.fuse(estimated)
        partial = estimated.partial
        if before is None or partial is None or partial.computed.all():
            continue
        gc.collect()
        assert before() is None  # the history this frame was fused into went, though its estimate is held
        assert partial.hint() is None
        checked += 1
    assert checked > 0  # bands were skipped in frames whose history had gone


def test_refresh_is_checked_and_colour_streams_ignore_it():
    import pytest

    from service.pipeline import PipelineConfig
    from svelive import SveliveError
    from svelive.reconstruction.live import LIVE_REFRESH

    for bad in (-1, 65, 2.5, True):
        with pytest.raises(SveliveError, match="refresh"):
            Reconstructor("1,4/16,64", refresh=bad)
        with pytest.raises(SveliveError, match="refresh"):
            PipelineConfig(refresh=bad)
    assert PipelineConfig().refresh == LIVE_REFRESH and Reconstructor("1,4/16,64").refresh == 0
    frames = _frames(2)
    colour = DemoSource("demo", width=128, height=128, fps=0, period_s=1e9)  # the demo's colour camera
    try:
        raw = next(iter(colour.frames(limit=1)))
    finally:
        colour.close()
    assert raw.camera.cfa is not None
    stream = Reconstructor(raw.camera, refresh=8)
    stream.process(raw)
    assert stream.last_partial is None and stream.refresh_state()["applies"] is False
    mono = Reconstructor(frames[0].camera, refresh=8)
    mono.process(frames[0])
    assert mono.refresh_state()["applies"] is True


def test_a_frame_estimated_and_never_fused_leaves_the_hints_aligned():
    """A frame the caller estimates and drops (a live service that gives up on it) takes no round-robin turn: the
    frames after it are estimated with the bands their fusion selects (no band added or dropped by fuse), and
    fuse as a stream that never saw it does."""
    raws, sensor = _moving_disc_raws(22)
    kw = dict(black_level=64, white_level=4095, gain=sensor.gain, read_noise=sensor.read_noise, refresh=4)
    dropping, plain = Reconstructor("1,4/16,64", **kw), Reconstructor("1,4/16,64", **kw)
    for i, raw in enumerate(raws):
        if i in (10, 15):
            dropping.estimate(raw)  # and never fused
            continue
        got, want = dropping.process(raw), plain.process(raw)
        np.testing.assert_array_equal(got.image, want.image, err_msg=f"frame {i}")
    state = dropping.refresh_state()
    assert state["hint_added"] == state["hint_dropped"] == 0, state
    assert plain.last_partial["computed"] < plain.last_partial["bands"]


def test_a_four_row_pattern_s_bands_cells_and_edges_give_the_full_frames_results():
    """1/1/8/8 (5-row windows, whose wide fallback reaches 22 rows: settle.halo_for gives 32 rows): the method on
    its bands, on demand in atlases (every cell of the frame) and edge stacks give the full frame's results bit for
    bit, bright and 8 stops dim (with a halo of 16 rows the dim frame's differed)."""
    demo = DemoSource("demo", width=328, height=200, fps=0, period_s=1e9, cfa="none", pattern="1/1/8/8")
    try:
        frame = next(iter(demo.frames(limit=1)))
    finally:
        demo.close()
    assert settle.halo_for(frame.camera.pattern) == (32, 16)
    for dim in (1.0, 2.0 ** -8):
        inp = _dimmed_input(frame, dim)
        noise = noise_model(inp)
        image, lower, variance, _, _, _ = _estimate(inp, noise, 1, want_variance=True)
        h, w = inp.shape
        hy, hx = settle.halo_for(inp.pattern)
        c = settle.CELL
        cells = np.array([(i, j) for i in range(h // c) for j in range(w // c)
                          if i * c >= hy and (i + 1) * c + hy <= h and j * c >= hx and (j + 1) * c + hx <= w])
        atlas, oy, ox = settle._atlas(inp, cells, 8)
        got = _estimate(atlas, noise, 1, want_variance=True)[:3]
        for (i, j), y, x in zip(cells, oy, ox):
            rows, cols = slice(i * c, i * c + c), slice(j * c, j * c + c)
            for g, want in zip(got, (image, lower, variance)):
                np.testing.assert_array_equal(g[i * c + y:i * c + c + y, j * c + x:j * c + c + x], want[rows, cols])
        bands = len(settle.bands(h))
        part = settle.Partial(inp, noise, np.zeros(bands, bool), np.zeros(h, bool))
        _assert_on_demand_is_the_full_frames(part, _needed(h, w, 4), (image, lower, variance))
        selected = np.arange(bands) % 2 == 1
        out = (np.zeros((h, w), np.float32), np.zeros((h, w), bool), np.zeros((h, w), np.float32),
               np.zeros((2, h, w), np.float32))
        settle.method_on_bands(inp, noise, selected, *out)
        rows = np.repeat(selected, settle.BAND_ROWS)[:h]
        for got_band, want in zip(out, (image, lower, variance)):
            np.testing.assert_array_equal(got_band[rows], want[rows])
