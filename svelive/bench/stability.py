"""Stability sweeps: controlled synthetic scenes with one difficulty axis each, run for every method.

Each sweep returns a :class:`Sweep` (difficulty values and, per method, the
error at each). Frames are small (96x96 by default) and seeds fixed, so the
whole suite runs in seconds and the tests in tests/test_stability.py can use it.

Error measures (lower is better):
- ``mean |log2 error|``: mean absolute error in stops against what the frame
  can tell, min(truth, full scale of the shortest exposure): above that the
  frame only says "at least", and a method cannot do better than the bound.
- ``relative RMS error``: RMS(out - truth) / mean(truth).

Colour cases (every colour layout, joint against split; :func:`colour_sweeps`):
- ``chroma error`` (stops): the spread max_c e_c - min_c e_c of the per-channel
  errors e_c = log2(out_c / truth_c): 0 when only brightness is wrong, so it
  measures false colour alone, and it does not depend on white balance. Against
  the truth: scaling a pixel does not change it, so a clipped pixel that keeps
  its hue at any brightness has none.
- ``luminance error`` (stops): |log2| distance of the output's luminance from
  the interval between what the frame can tell (the luminance of the truth
  with every channel capped at its shortest exposure's full scale, a lower
  bound) and the truth: 0 inside it, as any value there is consistent with a
  clipped reading.
- ``magenta/pink shift`` (stops): max(e_R, e_B) - e_G where positive, against
  the truth: green low against red or blue, what clipped highlights turn into.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Callable

import numpy as np

from svelive.bench.colour import ColourSetting
from svelive.bench.motion_cases import stream_sweeps
from svelive.bench.runner import Setting
from svelive.bench.scenes import BENCH_SENSOR
from svelive.bench.sweep import Sweep
from svelive.core.camera import COLOUR_LAYOUTS, Camera
from svelive.core.cfa import joint_period
from svelive.core.pattern import Pattern
from svelive.core.sensor import Sensor
from svelive.reconstruction.input import prepare
from svelive.reconstruction.methods import METHODS
from svelive.simulation import exposure_scale, simulate

SIZE = 96
PATTERN = "1,4/16,64"
SEED = 11


def stability_settings() -> list[Setting]:
    """Every registered method with default options, and the OpenCV baseline."""
    return [Setting(name, name) for name in METHODS] + [Setting("baseline", "baseline")]


def reconstruct_with(setting: Setting, raw: np.ndarray, pattern: Pattern | str, sensor: Sensor = BENCH_SENSOR) -> np.ndarray:
    """Reconstruct ``raw`` with a setting, float32 (H, W)."""
    return setting.run(prepare(raw, pattern, sensor)).image


def measurable(truth: np.ndarray, pattern: Pattern | str, sensor: Sensor = BENCH_SENSOR) -> np.ndarray:
    """What a frame can tell: truth capped at the radiance where the shortest exposure saturates."""
    return np.minimum(truth, sensor.censor_level / float(Pattern.parse(pattern).levels[0]))


def stops_error(out: np.ndarray, target: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean |log2(out / target)| (stops), values floored at 1e-3 DN; over ``mask`` if given."""
    err = np.abs(np.log2(np.maximum(out, 1e-3) / np.maximum(target, 1e-3)))
    return float(err[mask].mean() if mask is not None else err.mean())


def relative_rms(out: np.ndarray, truth: np.ndarray) -> float:
    """RMS(out - truth) / mean(truth)."""
    return float(np.sqrt(np.mean((out.astype(np.float64) - truth) ** 2)) / max(float(truth.mean()), 1e-12))


def slanted(size: int = SIZE, angle_deg: float = 5.0) -> tuple[np.ndarray, np.ndarray]:
    """Coordinates (u across, v along) of a grid rotated by ``angle_deg``, float64 (size, size) each, centred."""
    y, x = np.mgrid[0:size, 0:size].astype(np.float64) - (size - 1) / 2
    a = np.deg2rad(angle_deg)
    return x * np.cos(a) + y * np.sin(a), -x * np.sin(a) + y * np.cos(a)


def _run_sweep(sweep: Sweep, scenes: Callable[[float], tuple[np.ndarray, np.ndarray, str, str]],
               measure: Callable[[np.ndarray, np.ndarray, str], float], settings: list[Setting],
               sensor: Sensor = BENCH_SENSOR) -> Sweep:
    """``scenes(d)`` gives (raw, truth, pattern used to simulate, pattern given to the methods)."""
    for setting in settings:
        sweep.errors[setting.label] = []
    for d in sweep.difficulty:
        raw, truth, _, nominal = scenes(d)
        for setting in settings:
            out = reconstruct_with(setting, raw, nominal, sensor)
            sweep.errors[setting.label].append(measure(out, truth, nominal))
    return sweep


def _simulated(truth: np.ndarray, pattern: str, seed: int = SEED) -> np.ndarray:
    return simulate(truth, pattern, BENCH_SENSOR, seed=seed).raw


def edge_across_saturation(settings: list[Setting], pattern: str = PATTERN) -> Sweep:
    """A slanted step edge whose bright side climbs through the saturation of every exposure but the shortest."""
    sweep = Sweep("edge", "edge across saturation", "edge contrast (stops)", "mean |log2 error| near the edge",
                  [float(c) for c in np.arange(0.0, 10.01, 0.5)])
    u, _ = slanted()
    dark = 0.25 * BENCH_SENSOR.range_dn / float(Pattern.parse(pattern).levels[-1])
    band = np.abs(u) <= 3

    def scene(c: float):
        truth = np.where(u > 0, dark * 2.0**c, dark).astype(np.float32)
        return _simulated(truth, pattern), truth, pattern, pattern

    return _run_sweep(sweep, scene, lambda out, truth, p: stops_error(out, measurable(truth, p), band), settings)


def texture_frequency(settings: list[Setting], pattern: str = PATTERN) -> Sweep:
    """A slanted sinusoidal grating (contrast 1:3) from coarse to the sensor's Nyquist frequency."""
    sweep = Sweep("texture", "texture frequency (aliasing, moire)", "frequency (cycles / pixel, Nyquist 0.5)",
                  "relative RMS error", [float(f) for f in np.linspace(0.02, 0.5, 13)])
    u, _ = slanted(angle_deg=7.0)
    mean = 0.5 * BENCH_SENSOR.range_dn / float(Pattern.parse(pattern).levels[-1])

    def scene(f: float):
        truth = (mean * (1.0 + 0.5 * np.sin(2 * np.pi * f * u))).astype(np.float32)
        return _simulated(truth, pattern), truth, pattern, pattern

    return _run_sweep(sweep, scene, lambda out, truth, p: relative_rms(out, truth), settings)


def low_light(settings: list[Setting], pattern: str = PATTERN) -> Sweep:
    """A flat scene from half the longest exposure's full scale down by up to 14 stops (photon count, read noise)."""
    sweep = Sweep("low_light", "low light (photon count, read noise)", "stops below half fill of the longest exposure",
                  "relative RMS error", [float(s) for s in range(0, 15)])
    top = 0.5 * BENCH_SENSOR.range_dn / float(Pattern.parse(pattern).levels[-1])

    def scene(s: float):
        truth = np.full((SIZE, SIZE), top * 2.0**-s, np.float32)
        return _simulated(truth, pattern), truth, pattern, pattern

    return _run_sweep(sweep, scene, lambda out, truth, p: relative_rms(out, truth), settings)


def saturated_fraction(settings: list[Setting], pattern: str = PATTERN) -> Sweep:
    """A log ramp across the frame shifted so that a growing fraction of it saturates even the shortest exposure."""
    sweep = Sweep("saturation", "saturated fraction", "fraction of pixels beyond the shortest exposure",
                  "mean |log2 error| vs what the frame can tell", [float(f) for f in np.linspace(0, 1, 11)])
    levels = Pattern.parse(pattern).levels
    limit = BENCH_SENSOR.range_dn / float(levels[0])
    x = np.linspace(0, 1, SIZE)[None, :].repeat(SIZE, 0)
    span = 8.0  # stops across the frame

    def scene(f: float):
        truth = (limit * 2.0 ** (span * (x - (1.0 - f)))).astype(np.float32)  # column 1 - f sits at the limit
        return _simulated(truth, pattern), truth, pattern, pattern

    return _run_sweep(sweep, scene, lambda out, truth, p: stops_error(out, measurable(truth, p)), settings)


def _textured_scene(pattern: str) -> np.ndarray:
    """Smooth texture over ~6 stops that every exposure of ``pattern`` measures somewhere, float32 (SIZE, SIZE)."""
    u, v = slanted(angle_deg=11.0)
    levels = Pattern.parse(pattern).levels
    top = 0.5 * BENCH_SENSOR.range_dn / float(levels[0])
    return (top * 2.0 ** (-6.0 * (0.5 + 0.25 * np.sin(u / 9.0) + 0.25 * np.cos(v / 13.0)))).astype(np.float32)


def hot_dead_pixels(settings: list[Setting], pattern: str = PATTERN) -> Sweep:
    """Half hot (stuck at white) and half dead (stuck at black) pixels, up to 2% of the frame."""
    sweep = Sweep("defects", "hot and dead pixels", "fraction of defective pixels", "mean |log2 error|",
                  [float(f) for f in np.linspace(0, 0.02, 9)])
    truth = _textured_scene(pattern)
    clean = _simulated(truth, pattern)
    order = np.random.default_rng(SEED).permutation(truth.size)

    def scene(f: float):
        raw = clean.copy().ravel()
        n = int(round(f * raw.size))
        raw[order[: n // 2]] = int(BENCH_SENSOR.white_level)
        raw[order[n // 2: n]] = 0
        return raw.reshape(clean.shape), truth, pattern, pattern

    return _run_sweep(sweep, scene, lambda out, t, p: stops_error(out, measurable(t, p)), settings)


def phase_error(settings: list[Setting], pattern: str = PATTERN) -> Sweep:
    """The methods told a tile whose origin is off by 0 or 1 pixel in x, y or both."""
    sweep = Sweep("phase", "pattern phase off by one pixel", "offset: 0 none, 1 x, 2 y, 3 x and y",
                  "mean |log2 error|", [0.0, 1.0, 2.0, 3.0])
    truth = _textured_scene(pattern)
    raw = _simulated(truth, pattern)
    tile = Pattern.parse(pattern).tile

    def scene(code: float):
        shift = (int(code) // 2, int(code) % 2)
        told = Pattern(np.roll(tile, shift, axis=(0, 1)))
        return raw, truth, pattern, str(told)

    return _run_sweep(sweep, scene, lambda out, t, p: stops_error(out, measurable(t, pattern)), settings)


def exposure_ratio_error(settings: list[Setting], pattern: str = PATTERN) -> Sweep:
    """The true exposures other than the shortest are off by -10% .. +10% from the nominal tile the methods use."""
    sweep = Sweep("ratio", "exposure ratios wrong", "error of the true exposure ratios (%)", "mean |log2 error|",
                  [float(p) for p in np.arange(-10.0, 10.01, 2.5)])
    truth = _textured_scene(pattern)
    tile = Pattern.parse(pattern).tile

    def scene(percent: float):
        true_tile = np.where(tile > tile.min(), tile * (1 + percent / 100.0), tile)
        raw = _simulated(truth, str(Pattern(true_tile)))
        return raw, truth, str(Pattern(true_tile)), pattern

    return _run_sweep(sweep, scene, lambda out, t, p: stops_error(out, measurable(t, pattern)), settings)


SWEEPS: dict[str, Callable[[list[Setting]], Sweep]] = {
    "edge": edge_across_saturation,
    "texture": texture_frequency,
    "low_light": low_light,
    "saturation": saturated_fraction,
    "defects": hot_dead_pixels,
    "phase": phase_error,
    "ratio": exposure_ratio_error,
}


# ----- colour cases ------------------------------------------------------------------------------

#: Camera RGB of a white surface in daylight: green strongest, as in the raw data of real sensors
#: (daylight white-balance multipliers about 2 for red and 1.4 for blue), so green clips first.
CAMERA_WHITE = np.array([0.5, 1.0, 0.7], np.float32)


def colour_stability_settings() -> list[ColourSetting]:
    """The colour default and the split baseline, both with the default method."""
    return [ColourSetting("joint", "joint"), ColourSetting("split", "split")]


def colour_label(setting: ColourSetting, layout: str) -> str:
    return f"{setting.label} {layout}"


def measurable_rgb(truth: np.ndarray, camera: Camera) -> np.ndarray:
    """What a colour frame can tell, per channel: truth capped where the shortest exposure saturates."""
    return np.minimum(truth, camera.sensor.censor_level / float(camera.require_pattern().levels[0]))


def channel_errors(out: np.ndarray, target: np.ndarray) -> np.ndarray:
    """log2(out / target) per pixel and channel, float64 (H, W, 3); values floored at 1e-3 DN."""
    return np.log2(np.maximum(out, 1e-3) / np.maximum(target, 1e-3))


def chroma_error(out: np.ndarray, target: np.ndarray, mask: np.ndarray) -> float:
    """Mean over ``mask`` of the spread of the per-channel errors in stops (0: a pure brightness error)."""
    e = channel_errors(out, target)[mask]
    return float(np.mean(e.max(axis=-1) - e.min(axis=-1)))


def magenta_shift(out: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> float:
    """Mean over ``mask`` of max(0, max(e_R, e_B) - e_G) in stops: green too low against red or blue."""
    e = channel_errors(out, truth)[mask]
    return float(np.mean(np.maximum(np.maximum(e[:, 0], e[:, 2]) - e[:, 1], 0)))


def luminance_error(out: np.ndarray, low: np.ndarray, high: np.ndarray, mask: np.ndarray) -> float:
    """Mean over ``mask`` of the |log2| distance (stops) of the luminance of ``out`` from the interval
    [luminance(low), luminance(high)] (Rec. 709 weights; all (H, W, 3)): zipper and blur at edges."""
    from svelive.metrics import luminance

    y = np.log2(np.maximum(luminance(out), 1e-3))
    lo = np.log2(np.maximum(luminance(low), 1e-3))
    hi = np.log2(np.maximum(luminance(high), 1e-3))
    return float(np.maximum(np.maximum(lo - y, y - hi), 0)[mask].mean())


def _run_colour_sweep(sweep: Sweep, scene: Callable[[float, str], tuple[np.ndarray, np.ndarray]],
                      measure: Callable[[np.ndarray, np.ndarray, Camera], float], settings: list[ColourSetting],
                      layouts: tuple[str, ...]) -> Sweep:
    """``scene(d, layout)`` gives (raw, truth (H, W, 3)); one curve per setting and layout."""
    for layout in layouts:
        camera = Camera.build(layout, sensor=BENCH_SENSOR)
        curves = {colour_label(s, layout): [] for s in settings}
        for d in sweep.difficulty:
            raw, truth = scene(d, layout)
            inp = prepare(raw, camera)
            for s in settings:
                curves[colour_label(s, layout)].append(measure(s.run(inp), truth, camera))
        sweep.errors.update(curves)
    return sweep


def _simulated_rgb(truth: np.ndarray, layout: str, seed: int = SEED) -> np.ndarray:
    pattern, cfa = COLOUR_LAYOUTS[layout]
    return simulate(truth, pattern, BENCH_SENSOR, cfa=cfa, seed=seed).raw


def colour_edge(settings: list[ColourSetting], layouts: tuple[str, ...] = tuple(COLOUR_LAYOUTS)) -> tuple[Sweep, Sweep]:
    """A slanted black/white edge (white = :data:`CAMERA_WHITE`) whose bright side climbs through saturation.

    Returns two sweeps over the same frames: the chroma error within 3 px of the edge
    (false colour, colour zipper) and the luminance error there (zipper, blur). From 5
    stops of contrast the bright side's green clips in every exposure, from 6 every channel.
    """
    contrasts = [float(c) for c in np.arange(0.0, 10.01, 1.0)]
    chroma = Sweep("colour_edge", "colour: black/white edge, false colour", "edge contrast (stops)",
                   "chroma error near the edge (stops)", contrasts, log_y=True)
    luma = Sweep("colour_edge_luma", "colour: black/white edge, zipper", "edge contrast (stops)",
                 "luminance error near the edge (stops)", contrasts, log_y=True)
    u, _ = slanted()
    band = np.abs(u) <= 3
    frames: dict[tuple[float, str], tuple[np.ndarray, np.ndarray]] = {}

    def scene(c: float, layout: str):
        if (c, layout) not in frames:
            longest = float(Camera.build(layout).require_pattern().levels[-1])
            dark = 0.25 * BENCH_SENSOR.range_dn / longest
            level = np.where(u > 0, dark * 2.0**c, dark).astype(np.float32)
            truth = level[..., None] * CAMERA_WHITE
            frames[c, layout] = (_simulated_rgb(truth, layout), truth)
        return frames[c, layout]

    _run_colour_sweep(chroma, scene, lambda out, t, cam: chroma_error(out, t, band), settings, layouts)
    _run_colour_sweep(luma, scene, lambda out, t, cam: luminance_error(out, measurable_rgb(t, cam), t, band),
                      settings, layouts)
    return chroma, luma


def colour_edge_crops(layouts: tuple[str, ...] = tuple(COLOUR_LAYOUTS), contrasts: tuple[float, ...] = (3.0, 5.0),
                      settings: list[ColourSetting] | None = None, half: int = 18) -> list[dict[str, object]]:
    """What the user sees at the edge of :func:`colour_edge`: the centre of the frame rendered for display.

    Returns one entry per layout and contrast: ``{"layout", "contrast", "images": {label: float64
    (2 half, 2 half, 3) sRGB in [0, 1]}}`` for the truth and each setting, white-balanced by
    :data:`CAMERA_WHITE` (so white is white) and rendered with svelive.metrics.render_srgb at half the
    exposure the truth's log-average implies.
    """
    from svelive.metrics import render_exposure, render_srgb

    settings = colour_stability_settings() if settings is None else settings
    u, _ = slanted()
    centre = slice(SIZE // 2 - half, SIZE // 2 + half)
    out = []
    for layout in layouts:
        camera = Camera.build(layout, sensor=BENCH_SENSOR)
        dark = 0.25 * BENCH_SENSOR.range_dn / float(camera.require_pattern().levels[-1])
        for c in contrasts:
            truth = np.where(u > 0, dark * 2.0**c, dark).astype(np.float32)[..., None] * CAMERA_WHITE
            inp = prepare(_simulated_rgb(truth, layout), camera)
            images = {"truth": truth, **{s.label: s.run(inp) for s in settings}}
            exposure = 0.5 * render_exposure(truth)
            out.append({"layout": layout, "contrast": c, "images": {
                k: render_srgb(v[centre, centre] / CAMERA_WHITE, exposure) for k, v in images.items()}})
    return out


#: Peaks of the highlight sweep, in stops of its green channel above the shortest exposure's full scale;
#: red (half of green in CAMERA_WHITE) is measured up to +1 stop, so "only some channels clip" up to there.
HIGHLIGHT_PEAKS = (-3.0, -2.0, -1.0, -0.5, 0.0, 0.25, 0.5, 0.75, 1.5, 2.5)


def clipped_highlight(settings: list[ColourSetting],
                      layouts: tuple[str, ...] = tuple(COLOUR_LAYOUTS)) -> Sweep:
    """A white (:data:`CAMERA_WHITE`) Gaussian highlight on a dim grey ground, its peak rising until green,
    then blue, then red clip in every exposure: the magenta/pink shift inside the highlight (green above a
    quarter of its peak), against the truth."""
    sweep = Sweep("colour_highlight", "colour: clipped white highlight", "peak green (stops above the "
                  "shortest exposure's full scale)", "magenta/pink shift in the highlight (stops)",
                  list(HIGHLIGHT_PEAKS), log_y=False,
                  notes="beyond +1 stop every channel clips at the centre: the frame cannot tell the hue there")
    y, x = np.mgrid[0:SIZE, 0:SIZE].astype(np.float32) - (SIZE - 1) / 2
    profile = np.exp(-(x * x + y * y) / (2 * 14.0**2))
    core = profile >= 0.25

    def scene(peak: float, layout: str):
        full = BENCH_SENSOR.censor_level / float(Camera.build(layout).require_pattern().levels[0])
        level = full * 2.0**peak * profile + 0.02 * full
        truth = (level[..., None] * CAMERA_WHITE).astype(np.float32)
        return _simulated_rgb(truth, layout), truth

    return _run_colour_sweep(sweep, scene, lambda out, t, cam: magenta_shift(out, t, core), settings, layouts)


def colour_sweeps(settings: list[ColourSetting] | None = None,
                  layouts: tuple[str, ...] = tuple(COLOUR_LAYOUTS)) -> list[Sweep]:
    """The colour cases: the edge (false colour, zipper) and the clipped highlight."""
    settings = colour_stability_settings() if settings is None else settings
    return [*colour_edge(settings, layouts), clipped_highlight(settings, layouts)]


# ----- colour artefacts (issue 27): small coloured lights, line-pair staircase, dark specks -------------

#: A saturated orange light (white-balanced RGB; times :data:`CAMERA_WHITE` in camera RGB), as the
#: street lights of a city at dusk.
LIGHT_COLOUR = np.array([1.0, 0.45, 0.08], np.float32)
#: Side of the square light (pixels) and the spacing of the lights in the frame.
LIGHT_SIZE, LIGHT_SPACING = 3, 20
#: Light levels: its brightest channel's radiance, stops relative to the shortest exposure's full scale.
LIGHT_LEVELS = (-6.0, -4.0, -2.0, -1.0, -0.5)
#: Angle (degrees) of the staircase case's edge against the lines of the exposure pattern.
STAIR_ANGLE = 3.0
#: The staircase frame: (across, along) the edge, pixels; 256 along at 3 degrees crosses 13 rows.
STAIR_SHAPE = (48, 256)
STAIR_CONTRASTS = (2.0, 3.0, 4.0, 5.0)
#: Levels of the dark region, in read-noise deviations of a reading at the longest exposure.
SPECK_LEVELS = (0.25, 0.5, 1.0, 2.0, 4.0, 8.0)
#: A speck: a site whose channel reads below this fraction of its neighbourhood's (2 stops below).
SPECK_FRACTION = 0.25
#: The neighbourhood of a site in the speck count: a square of this side (pixels).
SPECK_WINDOW = 11


def chromaticity(rgb: np.ndarray) -> np.ndarray:
    """(r, b) chromaticity of white-balanced camera RGB (divided by :data:`CAMERA_WHITE`): R / (R + G + B)
    and B / (R + G + B), float64 (..., 2); (1/3, 1/3) where the sum is 0."""
    balanced = np.maximum(np.asarray(rgb, np.float64), 0) / CAMERA_WHITE
    total = balanced.sum(axis=-1, keepdims=True)
    safe = np.where(total > 0, total, 1.0)
    return np.where(total > 0, balanced[..., [0, 2]] / safe, 1.0 / 3.0)


def chromaticity_error(out: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Euclidean (r, b) chromaticity distance per site (:func:`chromaticity`), float64 (...): 0 for any
    brightness error; a white light where an orange one was is about 0.4."""
    return np.hypot(*np.moveaxis(chromaticity(out) - chromaticity(truth), -1, 0))


def light_phases(layout: str) -> list[tuple[int, int]]:
    """Every (row, col) phase of a layout's joint period (exposure pattern and CFA)."""
    camera = Camera.build(layout)
    py, px = joint_period(camera.require_pattern().shape, camera.cfa.shape)
    return [(dy, dx) for dy in range(py) for dx in range(px)]


def coloured_lights(layout: str, level: float, size: int = SIZE) -> tuple[np.ndarray, list[tuple[int, int]]]:
    """Camera RGB float32 (size + size // 4, size, 3) of :data:`LIGHT_COLOUR` lights, LIGHT_SIZE square, on
    black, one at every phase of the layout's joint period, and their top-left corners; below them a grey
    (:data:`CAMERA_WHITE`) band size // 4 rows high at a quarter of the lights' level, so that the frame's
    white balance has a neutral surface to find, as in a real scene. ``level``: stops of the light's
    brightest channel relative to the shortest exposure's full scale."""
    camera = Camera.build(layout, sensor=BENCH_SENSOR)
    full = BENCH_SENSOR.censor_level / float(camera.require_pattern().levels[0])
    colour = LIGHT_COLOUR * CAMERA_WHITE
    peak = np.float32(full * 2.0**level)
    colour = colour / colour.max() * peak
    truth = np.zeros((size + size // 4, size, 3), np.float32)
    truth[size:] = CAMERA_WHITE / CAMERA_WHITE.max() * (peak / 4)
    corners = []
    per_row = (size - LIGHT_SPACING // 2) // LIGHT_SPACING
    for n, (dy, dx) in enumerate(light_phases(layout)):
        y0 = LIGHT_SPACING // 2 + LIGHT_SPACING * (n // per_row) + dy
        x0 = LIGHT_SPACING // 2 + LIGHT_SPACING * (n % per_row) + dx
        truth[y0:y0 + LIGHT_SIZE, x0:x0 + LIGHT_SIZE] = colour
        corners.append((y0, x0))
    return truth, corners


def light_errors(out: np.ndarray, truth: np.ndarray, corners: list[tuple[int, int]]) -> np.ndarray:
    """Per light (float64 (n,)): the median over its LIGHT_SIZE^2 sites of the (r, b) chromaticity error."""
    errors = []
    for y0, x0 in corners:
        window = (slice(y0, y0 + LIGHT_SIZE), slice(x0, x0 + LIGHT_SIZE))
        errors.append(float(np.median(chromaticity_error(out[window], truth[window]))))
    return np.array(errors)


def coloured_light(settings: list[ColourSetting], layouts: tuple[str, ...] = tuple(COLOUR_LAYOUTS)) -> Sweep:
    """Small saturated coloured lights (3x3, orange) on black at every phase of the layout, their level rising
    to just below the shortest exposure's full scale: the chromaticity error at the lights (mean over phases)."""
    sweep = Sweep("colour_light", "colour: 3x3 orange lights on black, every phase", "light level (stops "
                  "relative to the shortest exposure's full scale)", "(r, b) chromaticity error at the light",
                  list(LIGHT_LEVELS), log_y=False,
                  notes="white instead of orange is about 0.4; the median of each light's 9 sites, mean over phases")
    frames: dict[tuple[float, str], tuple[np.ndarray, np.ndarray, list[tuple[int, int]]]] = {}

    def scene(level: float, layout: str):
        truth, corners = coloured_lights(layout, level)
        frames[level, layout] = (truth, truth, corners)
        return _simulated_rgb(truth, layout), truth

    def measure(out: np.ndarray, truth: np.ndarray, camera: Camera) -> float:
        corners = next(c for t, _, c in frames.values() if t is truth)
        return float(light_errors(out, truth, corners).mean())

    return _run_colour_sweep(sweep, scene, measure, settings, layouts)


def stair_axis(layout: str) -> tuple[int, int]:
    """(axis across the edge, period): the axis (0 rows, 1 columns) along which the layout's exposure
    pattern repeats with the larger period (rows on a tie), and that period (4 for dual-ISO's line pairs)."""
    shape = Camera.build(layout).require_pattern().shape
    axis = 0 if shape[0] >= shape[1] else 1
    return axis, shape[axis]


def stair_coverage(shape: tuple[int, int] = STAIR_SHAPE, angle_deg: float = STAIR_ANGLE,
                   supersample: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """An edge at ``angle_deg`` to the rows, (across, along) = ``shape``: the bright side's area in each pixel,
    float32 (shape), and the edge's true position across at each position along, float64 (shape[1],)."""
    n, m = shape
    step = 1.0 / supersample
    y, x = np.mgrid[0:n * supersample, 0:m * supersample] * step + step / 2 - 0.5
    slope = np.tan(np.deg2rad(angle_deg))
    edge = lambda u: n / 2 + (u - m / 2) * slope  # noqa: E731
    fine = (y > edge(x)).astype(np.float32)
    coverage = fine.reshape(n, supersample, m, supersample).mean(axis=(1, 3))
    return coverage.astype(np.float32), edge(np.arange(m, dtype=np.float64))


def edge_positions(lum: np.ndarray, low: float, high: float) -> np.ndarray:
    """Position of a step edge from ``low`` (first rows) to ``high`` in each column of ``lum`` (H, W), rows,
    float64 (W,): the rows' fraction of the way from low to high in log2, summed from the far side."""
    t = (np.log2(np.maximum(lum, 1e-6)) - np.log2(low)) / (np.log2(high) - np.log2(low))
    return (1.0 - np.clip(t, 0, 1)).sum(axis=0) - 0.5


def periodic_amplitude(residual: np.ndarray, position: np.ndarray, period: float) -> float:
    """Amplitude of the component of ``residual`` periodic in ``position`` with ``period``: 2 |mean(r e^(-i phi))|,
    phi = 2 pi position / period (both float (N,), positions spread over whole periods)."""
    phase = 2 * np.pi * np.asarray(position, np.float64) / period
    return float(2 * abs(np.mean(np.asarray(residual, np.float64) * np.exp(-1j * phase))))


def staircase_scene(layout: str, contrast: float) -> tuple[np.ndarray, np.ndarray, float, float]:
    """The staircase case's truth, camera RGB float32 (H, W, 3), laid across the layout's axis (rows for
    dual-ISO), the edge's true positions across, and the dark and bright levels of its luminance; the dark
    side at a quarter of the longest exposure's full scale, as :func:`colour_edge`."""
    axis, _ = stair_axis(layout)
    coverage, true_position = stair_coverage()
    longest = float(Camera.build(layout).require_pattern().levels[-1])
    dark = 0.25 * BENCH_SENSOR.range_dn / longest
    level = dark * (1 + (2.0**contrast - 1) * coverage)
    truth = (level[..., None] * CAMERA_WHITE).astype(np.float32)
    if axis == 1:
        truth = np.ascontiguousarray(truth.transpose(1, 0, 2))
    return truth, true_position, dark, dark * 2.0**contrast


def staircase_amplitude(out: np.ndarray, layout: str, truth: np.ndarray, true_position: np.ndarray,
                        low: float, high: float, margin: int = 8) -> float:
    """The staircase (pixels): the component of the edge position's error (out against the truth, both
    estimated by :func:`edge_positions` on luminance) periodic with the layout's period in the true position,
    over the edge less ``margin`` pixels at each end."""
    axis, period = stair_axis(layout)
    weights = CAMERA_WHITE / float(np.sum(CAMERA_WHITE * CAMERA_WHITE))  # the luminance of a white surface
    lum_out, lum_truth = out @ weights, truth @ weights
    if axis == 1:
        lum_out, lum_truth = lum_out.T, lum_truth.T
    residual = edge_positions(lum_out, low, high) - edge_positions(lum_truth, low, high)
    inside = slice(margin, residual.size - margin)
    return periodic_amplitude(residual[inside], true_position[inside], period)


def staircase(settings: list[ColourSetting], layouts: tuple[str, ...] = tuple(COLOUR_LAYOUTS)) -> Sweep:
    """A grey edge at 3 degrees to the exposure pattern's lines (line pairs of dual-ISO), contrast rising until
    the bright side clips every exposure but the shortest: the staircase amplitude of the edge (pixels)."""
    sweep = Sweep("colour_staircase", "colour: edge across line pairs, staircase", "edge contrast (stops)",
                  "staircase amplitude at the pattern's period (px)", list(STAIR_CONTRASTS), log_y=False)
    cases: dict[tuple[float, str], tuple[np.ndarray, np.ndarray, float, float]] = {}

    def scene(contrast: float, layout: str):
        case = staircase_scene(layout, contrast)
        cases[contrast, layout] = case
        return _simulated_rgb(case[0], layout), case[0]

    def measure(out: np.ndarray, truth: np.ndarray, camera: Camera) -> float:
        (_, layout), (_, position, low, high) = next((k, v) for k, v in cases.items() if v[0] is truth)
        return staircase_amplitude(out, layout, truth, position, low, high)

    return _run_colour_sweep(sweep, scene, measure, settings, layouts)


def dark_region(layout: str, level: float, size: int = SIZE) -> tuple[np.ndarray, np.ndarray]:
    """A flat grey (:data:`CAMERA_WHITE`) region ``level`` read-noise deviations of the longest exposure,
    with four bright lights (discs of radius 3 px at the shortest exposure's full scale) so that the frame
    is exposed for them: camera RGB (size, size, 3) float32, and the mask (size, size) of sites whose whole
    SPECK_WINDOW neighbourhood lies at least 10 px from every light's centre (a neighbourhood reaching a
    light's halo would make a flat site read "below its neighbourhood": a halo, not a speck)."""
    camera = Camera.build(layout, sensor=BENCH_SENSOR)
    levels = camera.require_pattern().levels
    flat = level * np.sqrt(BENCH_SENSOR.floor_variance) / float(levels[-1])
    full = BENCH_SENSOR.censor_level / float(levels[0])
    y, x = np.mgrid[0:size, 0:size].astype(np.float32)
    level_map = np.full((size, size), flat, np.float32)
    far = np.ones((size, size), bool)
    for cy, cx in ((0.2, 0.3), (0.25, 0.8), (0.75, 0.2), (0.8, 0.7)):
        r2 = (y - cy * size) ** 2 + (x - cx * size) ** 2
        level_map[r2 <= 3.0**2] = full
        far &= r2 >= (10.0 + SPECK_WINDOW // 2) ** 2
    return (level_map[..., None] * CAMERA_WHITE).astype(np.float32), far


def speck_fraction(out: np.ndarray, mask: np.ndarray) -> float:
    """Percentage of the sites in ``mask`` where some channel of ``out`` (H, W, 3) reads below
    SPECK_FRACTION of the mean of that channel over its SPECK_WINDOW-square neighbourhood."""
    import cv2

    low = np.zeros(mask.shape, bool)
    for c in range(3):
        channel = np.ascontiguousarray(out[..., c], np.float32)
        around = cv2.blur(channel, (SPECK_WINDOW, SPECK_WINDOW), borderType=cv2.BORDER_REFLECT)
        low |= channel < SPECK_FRACTION * around
    return float(100.0 * low[mask].mean())


def dark_specks(settings: list[ColourSetting], layouts: tuple[str, ...] = tuple(COLOUR_LAYOUTS)) -> Sweep:
    """A dim flat region beside bright lights (a frame exposed for the lights): the percentage of its sites
    reading 2 stops or more below their neighbourhood in some channel (dark specks)."""
    sweep = Sweep("colour_specks", "colour: dim flat region, dark specks", "region level (read-noise "
                  "deviations at the longest exposure)", "sites 2 stops below their neighbourhood (%)",
                  list(SPECK_LEVELS), log_y=False)
    masks: dict[int, np.ndarray] = {}

    def scene(level: float, layout: str):
        truth, far = dark_region(layout, level)
        masks[id(truth)] = far
        return _simulated_rgb(truth, layout), truth

    return _run_colour_sweep(sweep, scene, lambda out, t, cam: speck_fraction(out, masks[id(t)]), settings, layouts)


def artefact_sweeps(settings: list[ColourSetting] | None = None,
                    layouts: tuple[str, ...] = tuple(COLOUR_LAYOUTS)) -> list[Sweep]:
    """Issue 27's colour artefact cases: small coloured lights, the line-pair staircase, dark specks."""
    settings = colour_stability_settings() if settings is None else settings
    return [coloured_light(settings, layouts), staircase(settings, layouts), dark_specks(settings, layouts)]


def run_stability(settings: list[Setting] | None = None, colour: bool = True) -> list[dict[str, object]]:
    """Every sweep for every setting, the library stream's cases (svelive.bench.motion_cases: moving-pixel
    loss, trail and still-region gain against the single frame) and the colour cases for joint and split,
    JSON-ready."""
    settings = stability_settings() if settings is None else settings
    sweeps = [asdict(make(settings)) for make in SWEEPS.values()]
    sweeps += [asdict(sweep) for sweep in stream_sweeps()]
    if colour:
        sweeps += [asdict(sweep) for sweep in (*colour_sweeps(), *artefact_sweeps())]
    return sweeps


# ----- the default's guard grid (issue 12): the default against aggregate and weighted in every cell -----

#: Patterns of the grid: both 2x2 tiles, the line-interleaved one and a 3x3 tile (each row and column holds
#: every exposure).
GRID_PATTERNS: tuple[str, ...] = ("1,4/16,64", "1,2/4,8", "1/1/8/8", "1,4,16/16,1,4/4,16,1")
#: Light: stops by which the scene's 99.9th percentile lies below the lowest exposure's full scale.
GRID_STOPS: tuple[float, ...] = (0.0, 3.0, 5.0, 7.0)
#: The noise model given to the methods, as factors on the true (gain, read noise); None: not given (estimated).
GRID_MODELS: dict[str, tuple[float, float] | None] = {
    "estimated": None, "true": (1.0, 1.0), "read x0.5": (1.0, 0.5), "read x2": (1.0, 2.0),
    "gain x0.5": (0.5, 1.0), "gain x2": (2.0, 1.0)}
#: The methods the default must not lose to, and the margin it may lose by (dB).
GRID_RIVALS: tuple[str, ...] = ("aggregate", "weighted")
GRID_TOLERANCE_DB = 0.3
GRID_SEED = 0


@dataclass(frozen=True)
class TrueSensor:
    """A sensor the grid's frames are simulated with: 12 bits, black 64, its full well and read noise."""

    name: str
    full_well_e: float
    read_noise_dn: float

    def sensor(self) -> Sensor:
        gain = self.full_well_e / (4095.0 - 64.0)
        return Sensor(12, 64.0, 4095.0, gain, self.read_noise_dn)


#: The true sensors: the issue's (10 000 e- full well, read noise 2 DN) and a small-pixel one (3 000 e-, 4 DN).
GRID_SENSORS: tuple[TrueSensor, ...] = (TrueSensor("10000e-/2DN", 10_000.0, 2.0),
                                        TrueSensor("3000e-/4DN", 3_000.0, 4.0))


@dataclass(frozen=True)
class GridConfig:
    """What a grid run covers (every combination of these)."""

    patterns: tuple[str, ...] = GRID_PATTERNS
    stops: tuple[float, ...] = GRID_STOPS
    models: tuple[str, ...] = tuple(GRID_MODELS)
    sensors: tuple[TrueSensor, ...] = GRID_SENSORS
    seed: int = GRID_SEED


def quick_grid_config() -> GridConfig:
    """The issue's sensor only: half the cells."""
    return GridConfig(sensors=GRID_SENSORS[:1])


def given_noise(true: Sensor, model: str) -> dict[str, float | None]:
    """The ``gain`` and ``read_noise`` keywords of :func:`svelive.reconstruct` for a noise model of GRID_MODELS."""
    factors = GRID_MODELS[model]
    if factors is None:
        return {"gain": None, "read_noise": None}
    return {"gain": true.gain * factors[0], "read_noise": true.read_noise * factors[1]}


class _Scores:
    """PU21-PSNR and log-PSNR (svelive.metrics) against one truth, its encodings computed once."""

    def __init__(self, truth: np.ndarray) -> None:
        from svelive.metrics import PU21_PEAK, display_scale, pu21_encode

        self._encode, self._peak = pu21_encode, PU21_PEAK
        self._scale = display_scale(truth)
        self._pu21 = pu21_encode(truth * self._scale)
        self._floor = 1e-4 * float(np.percentile(truth, 99.9))
        self._log = np.log2(np.maximum(truth, self._floor))
        self._log_peak = float(self._log.max() - self._log.min()) or 1.0

    def __call__(self, image: np.ndarray) -> tuple[float, float]:
        """(PU21-PSNR, log-PSNR) of ``image``, dB: metrics.pu21_psnr and metrics.log_psnr against the truth."""
        pu21 = _psnr(self._encode(image * self._scale), self._pu21, self._peak)
        return pu21, _psnr(np.log2(np.maximum(image, self._floor)), self._log, self._log_peak)


def _psnr(a: np.ndarray, b: np.ndarray, peak: float) -> float:
    mse = float(np.mean((a - b) ** 2))
    return float("inf") if mse == 0 else float(10.0 * np.log10(peak * peak / mse))


def grid_scene_rows(name: str, scene: np.ndarray, config: GridConfig, default: str | None = None,
                    log: Callable[[str], None] | None = None) -> list[dict[str, object]]:
    """Every cell of one scene (linear luminance, float32 (H, W)): one row per (pattern, light, sensor, model).

    A row holds PU21-PSNR and log-PSNR of the default and of each rival, and the
    margins default - best rival (dB; negative: the default loses). ``aggregate``
    does not use the noise model, so it runs once per frame.
    """
    from svelive.reconstruction.methods import DEFAULT_METHOD
    from svelive.reconstruction.single import reconstruct

    default = DEFAULT_METHOD if default is None else default
    rows = []
    for true in config.sensors:
        sensor = true.sensor()
        for pattern in config.patterns:
            for stops in config.stops:
                radiance = scene * np.float32(exposure_scale(scene, Pattern.parse(pattern), sensor,
                                                             stops_below_fill=stops))
                frame = simulate(radiance, pattern, sensor, seed=config.seed)
                score = _Scores(frame.truth)
                levels = {"black_level": sensor.black_level, "white_level": sensor.white_level}
                fixed = {m: score(reconstruct(frame.raw, pattern, method=m, **levels))
                         for m in (default, *GRID_RIVALS) if m == "aggregate"}
                cells = []
                for model in config.models:
                    noise = given_noise(sensor, model)
                    scores = {m: fixed.get(m) or score(reconstruct(frame.raw, pattern, method=m, **levels, **noise))
                              for m in (default, *GRID_RIVALS)}
                    row: dict[str, object] = {"image": name, "pattern": pattern, "stops": 0.0 - stops,
                                              "sensor": true.name, "model": model}
                    for m, (pu21, logp) in scores.items():
                        row[f"{m}_pu21"], row[f"{m}_log"] = pu21, logp
                    for metric in ("pu21", "log"):
                        best = max(scores[m][0 if metric == "pu21" else 1] for m in GRID_RIVALS)
                        row[f"margin_{metric}"] = row[f"{default}_{metric}"] - best
                    rows.append(row)
                    cells.append(row)
                if log is not None:
                    worst = min(cells, key=lambda r: min(r["margin_pu21"], r["margin_log"]))
                    log(f"{name} {pattern} {-stops:+g} stops {true.name}: worst margin "
                        f"PU21 {worst['margin_pu21']:+.2f} log {worst['margin_log']:+.2f} dB ({worst['model']})")
    return rows


def grid_summary(rows: list[dict[str, object]], default: str, worst: int = 12) -> dict[str, object]:
    """Means over the grid per method and metric, the failing cells (margin below -GRID_TOLERANCE_DB) and the worst."""
    methods = (default, *GRID_RIVALS)
    means = {f"{m}_{metric}": float(np.mean([r[f"{m}_{metric}"] for r in rows]))
             for m in methods for metric in ("pu21", "log")}
    key = lambda r: min(r["margin_pu21"], r["margin_log"])  # noqa: E731
    failing = [r for r in rows if key(r) < -GRID_TOLERANCE_DB]
    return {"default": default, "cells": len(rows), "means": means, "failing": len(failing),
            "worst": sorted(rows, key=key)[:worst]}


def markdown_grid(summary: dict[str, object]) -> str:
    """The grid's means and worst cells as Markdown."""
    d = summary["default"]
    means = summary["means"]
    lines = [f"Grid: {summary['cells']} cells; default `{d}` loses by more than {GRID_TOLERANCE_DB} dB "
             f"in {summary['failing']}.", "",
             "| method | mean PU21-PSNR | mean log-PSNR |", "|---|---:|---:|"]
    for m in (d, *GRID_RIVALS):
        lines.append(f"| {m} | {means[f'{m}_pu21']:.2f} | {means[f'{m}_log']:.2f} |")
    lines += ["", "| image | pattern | stops | sensor | model | margin PU21 | margin log |",
              "|---|---|---:|---|---|---:|---:|"]
    for r in summary["worst"]:
        lines.append(f"| {r['image']} | {r['pattern']} | {r['stops']:g} | {r['sensor']} | {r['model']} |"
                     f" {r['margin_pu21']:+.2f} | {r['margin_log']:+.2f} |")
    return "\n".join(lines) + "\n"


def run_grid(scenes: dict[str, np.ndarray], config: GridConfig = GridConfig(), default: str | None = None,
             log: Callable[[str], None] | None = print) -> dict[str, object]:
    """The grid over ``scenes`` (name -> linear luminance): {"config", "rows", "summary"}, JSON-ready."""
    from svelive.reconstruction.methods import DEFAULT_METHOD

    default = DEFAULT_METHOD if default is None else default
    rows = [row for name, scene in scenes.items() for row in grid_scene_rows(name, scene, config, default, log)]
    return {"config": {**asdict(config), "rivals": list(GRID_RIVALS), "tolerance_db": GRID_TOLERANCE_DB},
            "rows": rows, "summary": grid_summary(rows, default)}
