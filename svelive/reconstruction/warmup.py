"""Kernel warm-up: compile, or load from numba's disk cache, every kernel a stream can run."""

from __future__ import annotations

from collections.abc import Iterable
from itertools import product

import numpy as np

from svelive.core.camera import COLOUR_LAYOUTS, Camera
from svelive.core.pattern import Pattern
from svelive.core.sensor import Sensor
from svelive.reconstruction.fusion import FUSE_ROWS
from svelive.reconstruction.methods import METHODS
from svelive.reconstruction.stream import EXPOSURE_TIMINGS, Reconstructor


def warm_up(methods: Iterable[str] | None = None) -> None:
    """Compile, or load from numba's disk cache, every kernel a stream of these methods runs.

    A kernel compiles on its first call (about a second each on a fresh
    machine); a service or an image build calls this once so that no live
    frame waits for it. Runs a few tiny synthetic frames (without and with
    saturated pixels, which take different paths) through a temporal
    Reconstructor per method and kind of pattern,
    with ``mask`` and ``integration`` exposure timing (the latter runs the
    within-frame test, whose output variance is also computed), and the preview
    tone map. Then the same for colour cameras (svelive.reconstruction.colour:
    cells 2 and 4 columns wide, which take loops of their own, and other widths;
    a per-pixel exposure map), and a single-frame joint colour reconstruction (the
    ``split`` baseline is not warmed: no stream runs it). ``methods``: default
    every method but ``cubic`` (numpy only). The frames are uint16; other raw
    types are converted to float32 before any kernel, so they need nothing more.
    """
    from svelive.tonemap import ToneMapper  # only the preview uses it

    rng = np.random.default_rng(0)
    # still, so that frames after the first fuse with the history; taller than a strip of the fusion,
    # whose rows around the strips' joins take a detail step of their own
    scene = rng.uniform(0, 200, (FUSE_ROWS + 8, 32))
    clean = [np.clip(rng.normal(scene, 3), 0, 4095).astype(np.uint16) for _ in range(3)]
    saturated = [frame.copy() for frame in clean]
    for frame in saturated:
        frame[:2, :4] = 4095
    # a few pixels that cannot tell their level from 0 amid brighter ones: adaptive's wide fallback sums their
    # blocks pixel by pixel (_wide_direct); the frames above hold many, whose blocks take box filters
    speck = [np.clip(frame.astype(np.int32) + 50, 0, 4095).astype(np.uint16) for frame in clean]
    for frame in speck:
        frame[60:62, 12:14] = 0
    nominal = Pattern.parse("1,4/16,64")
    # kernels take other paths for other tiles (1/1/8/8) and for calibrated per-pixel exposure maps
    patterns = [nominal, Pattern.parse("1/1/8/8"), nominal.with_pixel_map(nominal.exposure_map(scene.shape))]
    for method in methods if methods is not None else [m for m in METHODS if m != "cubic"]:
        for pattern, timing in product(patterns, EXPOSURE_TIMINGS):
            if timing == "integration" and pattern.pixel_map is not None:
                continue  # the within-frame test needs a nominal tile
            kinds = (clean, saturated, speck) if method == "adaptive" and timing == "mask" else (clean, saturated)
            for frames in kinds:
                reconstructor = Reconstructor(pattern, method=method, white_level=4095, exposure_timing=timing)
                for frame in frames:
                    result = reconstructor.process(frame)
                result.variance  # noqa: B018 (computed on demand: the within-frame test's variance kernel)
    if methods is None or "adaptive" in methods:
        _warm_up_refresh(rng)
    ToneMapper()(result.image, 0)
    _warm_up_colour(methods if methods is not None else [m for m in METHODS if m != "cubic"], clean, saturated, speck)


def _warm_up_refresh(rng: np.random.Generator) -> None:
    """The band refresh of live streams (``Reconstructor(refresh=K)``, svelive.reconstruction.settle; the service's
    default), monochrome and colour (``colour_refresh``): still frames of four bands (the noise model given, so trusted at once) until the
    histories settle and bands are skipped, then frames in which small patches change and frames that move a
    little and a lot (pixels reset in skipped bands take their estimate on demand: in cells, whose atlas of
    patches has writable exposures and, without a saturated pixel, the pattern's cached window sums, at the
    frame's edges and in whole bands), with and without saturated pixels,
    and a frame estimated ahead of the one before it (the fusion completes the bands its hint missed). The
    frames are wide and noisy enough for ``adaptive``'s floor evidence to find its pairs of readings dominated by
    the noise floor (``evidence._read_variance``, which every full-size live frame runs and the small frames
    above never reach)."""
    from svelive.reconstruction.settle import BAND_ROWS

    scene = rng.uniform(0, 1500, (3 * BAND_ROWS + 8, 128))
    sensor = Sensor(12, white_level=4095, gain=1.0, read_noise=20.0)
    # monochrome, then the same frames as Bayer mosaics through a colour stream's band refresh (``colour_refresh``:
    # the folded luminance's skipped rows take numerics' per-pixel window pass)
    for pattern, saturate, cfa in product(("1,4/16,64", "1/1/8/8"), (False, True), (None, "RGGB")):
        stream = Reconstructor(Camera.build(pattern, cfa, sensor), refresh=2, colour_refresh=True)
        frames = []
        # the still view, then with a small patch 600 DN brighter, then darker, in the middle of one band and at
        # the edge of the next (bands the refresh skips in one of the two frames), then moves
        for moved, patch in [(0, 0)] * 11 + [(0, 600), (0, -600), (1, 0), (30, 0), (30, 0), (0, 0)]:
            view = np.roll(scene, moved, axis=1)
            view[BAND_ROWS + 8:BAND_ROWS + 10, 56:58] += patch
            view[2 * BAND_ROWS + 8:2 * BAND_ROWS + 10, -2:] += patch
            frame = np.clip(rng.normal(view, 20), 0, 4095).astype(np.uint16)
            if saturate:
                frame[BAND_ROWS:BAND_ROWS + 2, :6] = 4095
            frames.append(frame)
        for frame in frames[:-2]:
            stream.process(frame)
        ahead = [stream.estimate(frame) for frame in frames[-2:]]
        for estimated in ahead:
            stream.fuse(estimated).variance  # noqa: B018 (computed on demand)


def _warm_up_colour(methods: Iterable[str], clean: list[np.ndarray], saturated: list[np.ndarray],
                    speck: list[np.ndarray]) -> None:
    """The colour half of :func:`warm_up` on the same frames, read as colour mosaics (``speck``: adaptive's
    wide fallback pixel by pixel, whose exposures are a folded frame's, not a pattern's read-only map)."""
    from svelive.reconstruction.single import reconstruct

    sensor = Sensor(12)
    shape = clean[0].shape
    nominal = Pattern.parse("1,4/16,64")
    cameras = [Camera.build("1,4/16,64", "RGGB", sensor),  # cells 2 x 2
               Camera.build("1,4/16,64", "R,G,B/G,B,R", sensor),  # 2 x 6: the general loop
               Camera(nominal.with_pixel_map(nominal.exposure_map(shape)), Camera.build(None, "RGGB").cfa, sensor)]
    # every layout of the library: their tiles give the methods' windows of other sizes (a 5-tap row window
    # takes adaptive's censored steps through OpenCV, _split_censored) and fusion its OpenCV detail path
    cameras += [Camera.build(layout, sensor=sensor) for layout in COLOUR_LAYOUTS]
    for method in methods:
        for camera, timing in product(cameras, EXPOSURE_TIMINGS):
            if timing == "integration" and camera.pattern.pixel_map is not None:
                continue
            kinds = (clean, saturated, speck) if method == "adaptive" and timing == "mask" else (clean, saturated)
            for frames in kinds:
                reconstructor = Reconstructor(camera, method=method, exposure_timing=timing)
                for frame in frames:
                    result = reconstructor.process(frame)
                result.variance  # noqa: B018
        # single joint frames colour with folding.colourise (a stream colours in its refinement's pass): cells of
        # 6 columns give it the shares' rows as a strided view, as a frame whose width no cell divides does
        for frames, camera in product((clean, saturated), (cameras[1], cameras[3])):
            reconstruct(frames[0], camera, method=method, return_confidence=True)
