"""The prototype of issue 25 (svelive.reconstruction.settle): ``adaptive`` on bands, cells and edge stacks gives the
full frame's results bit for bit; ``refresh=K`` streams skip bands and stay close to the stream without it."""

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


def test_bands_cells_and_edges_give_the_full_frames_results():
    frame = _frames(1)[0]
    for dim in (1.0, 2.0 ** -8):  # bright (censored readings), and dim (the wide fallback)
        raw = frame.raw
        if dim != 1.0:
            black = frame.camera.sensor.black_level
            raw = (np.round((raw.astype(np.float32) - black) * dim) + black).astype(raw.dtype)
        inp = prepare(raw, frame.camera)
        noise = noise_model(inp)
        image, lower, variance, _, _, window = _estimate(inp, noise, 1, want_variance=True, want_window=True)
        h, w = inp.shape
        bands = len(settle.bands(h))
        rng = np.random.default_rng(3)
        need = np.zeros((h, w), bool)
        need[rng.integers(0, h, 40), rng.integers(0, w, 40)] = True
        for y, x in [(0, 0), (0, w - 1), (h - 1, 0), (h - 1, w - 1), (3, 100), (h - 2, 50), (90, 1), (91, w - 1)]:
            need[y, x] = True
        part = settle.Partial(inp, noise, np.zeros(bands, bool), np.zeros(h, bool))
        ys, xs, (i2, l2, v2), _ = settle.on_demand(part, *np.nonzero(need))
        assert ys.size == np.count_nonzero(need)
        np.testing.assert_array_equal(i2, image[ys, xs])
        np.testing.assert_array_equal(l2, lower[ys, xs])
        np.testing.assert_array_equal(v2, variance[ys, xs])
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


def test_a_refresh_stream_skips_bands_of_a_still_view_and_stays_close():
    frames = _frames(14, 328, 400)
    off, on = Reconstructor(frames[0].camera), Reconstructor(frames[0].camera, refresh=4)
    computed = []
    for f in frames:
        a, b = off.process(f), on.process(f)
        p = on.last_partial  # (None while the estimated noise model is not trusted: the method everywhere)
        computed.append(1.0 if p is None else p["computed"] / p["bands"])
        assert np.isfinite(b.image).all() and (b.image >= 0).all()
    assert min(computed[9:]) < 0.75  # bands skipped once the history settled
    rel = np.abs(b.image - a.image) / np.maximum(a.image, 1.0)
    assert float(np.sqrt(np.mean(rel ** 2))) < 0.03
