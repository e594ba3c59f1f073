"""Moving-scene cases of the library's stream against the single-frame default (issue 26.2-4), with a trail metric.

Each case is a dim scene (its 99.9th percentile ``stops`` under the shortest exposure's full scale) with a
bright textured object that crosses it, stops, or starts, or a cut to another scene. Frames are rendered with
a true sensor the streams are not told (:func:`run_case`), and each stream is compared frame by frame with
``svelive.reconstruct`` of the same raw frame (the single-frame default, its noise model estimated from the
frame) on:

- ``still``: pixels whose truth has not moved in this frame or the three before;
- ``moving``: the ground-truth motion mask of the frame;
- ``trail``: pixels that moved in one of the last three frames and are still now, PU21 and the
  **ghost residue**: the share of the change a pixel went through that its output still shows,
  ``(out - truth) / (before - truth)`` (``before``: its truth in the frame before the change), averaged
  over the trail pixels whose change exceeds a fifth of the larger value; clipped to [-1, 1] per pixel.
  A history that leaks shows it as a positive mean (a pixel fused over n frames of which one was the old
  value keeps 1 / n of the change); noise averages to about 0. Reported as the stream's minus the single
  frame's.

Scenes are functions of time (svelive.scenes). ``moving_texture`` is a disc cut from another image, its
texture moving with it; ``stopping``/``starting`` re-time a scene; ``cut`` switches scenes between frames.
``procedural_scene`` makes an HDR scene that is in no image set (log-normal 1/f texture), for judging
on scenes the method was not developed on.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from svelive.bench.sweep import Sweep
from svelive.core.pattern import Pattern
from svelive.core.sensor import Sensor
from svelive.scenes import Scene, panning, render_sequence
from svelive.simulation import exposure_scale

#: frames a pixel stays in the trail region after it moved (as benchmarks/motion.py)
TRAIL_FRAMES = 3
#: a trail pixel's change counts for the ghost residue when it exceeds this share of the larger value
GHOST_CHANGE = 0.2


def moving_texture(background: np.ndarray, texture: np.ndarray, radius: float, start: tuple[float, float],
                   velocity: tuple[float, float]) -> Scene:
    """A disc of ``texture`` (float32 (h, w), radiance DN at exposure 1, at least 2 ``radius`` + 2 on a side)
    centred at ``start`` (rows, cols) at t = 0 and moving by ``velocity`` per frame over ``background``
    (float32 (H, W)); the texture moves with the disc, its centre at the disc's, edges anti-aliased."""
    background = np.asarray(background, np.float32)
    shape = background.shape
    th, tw = texture.shape
    # texture(t) = the texture's centre at the disc's: a crop window over it moving the other way
    inner = panning(texture, shape, (-velocity[0], -velocity[1]), (th / 2 - start[0], tw / 2 - start[1]))
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float32)

    def scene(t: float) -> np.ndarray:
        cy, cx = start[0] + velocity[0] * t, start[1] + velocity[1] * t
        cover = np.clip(radius + 0.5 - np.hypot(yy - cy, xx - cx), 0, 1)
        return background + cover * (inner(t) - background)

    return scene


def stopping(scene: Scene, at: float) -> Scene:
    """``scene`` frozen from time ``at`` (frames) on: a moving object that stops."""
    return lambda t: scene(min(t, at))


def starting(scene: Scene, at: float) -> Scene:
    """``scene`` held at its t = 0 until ``at``, then running: an object that starts moving."""
    return lambda t: scene(max(t - at, 0.0))


def cut(first: Scene, second: Scene, at: int) -> Scene:
    """``first`` before frame ``at``, ``second`` from it on (a whole frame on either side)."""
    return lambda t: first(t) if t < at else second(t)


def procedural_scene(shape: tuple[int, int], seed: int, stops: float = 10.0, slope: float = 2.0) -> np.ndarray:
    """A scene in no image set: float32 (H, W) > 0, ``2 ** (stops * u)`` with u a 1/f^(slope/2)-amplitude
    Gaussian field scaled to [-0.5, 0.5] (edges and texture at every scale, ``stops`` of dynamic range)."""
    rng = np.random.default_rng(seed)
    fy = np.fft.fftfreq(shape[0])[:, None]
    fx = np.fft.rfftfreq(shape[1])[None, :]
    amplitude = 1.0 / np.maximum(np.hypot(fy, fx), 1.0 / max(shape)) ** (slope / 2 + 0.5)
    spectrum = amplitude * (rng.standard_normal(amplitude.shape) + 1j * rng.standard_normal(amplitude.shape))
    field = np.fft.irfft2(spectrum, s=shape)
    u = (field - field.min()) / max(float(np.ptp(field)), 1e-12) - 0.5
    return np.exp2(stops * u).astype(np.float32)


def dim(image: np.ndarray, pattern: str, sensor: Sensor, stops: float) -> np.ndarray:
    """``image`` scaled so that its 99.9th percentile lies ``stops`` under the shortest exposure's full scale."""
    return image * exposure_scale(image, Pattern.parse(pattern), sensor, stops_below_fill=stops)


def ghost_residue(out: np.ndarray, truth: np.ndarray, before: np.ndarray, region: np.ndarray) -> float:
    """Mean share of the change ``before -> truth`` that ``out`` still shows over ``region`` (float32 (H, W)
    arrays, bool region), pixels whose change exceeds :data:`GHOST_CHANGE` of the larger value; nan if none."""
    change = before - truth
    use = region & (np.abs(change) > GHOST_CHANGE * np.maximum(np.abs(before), np.abs(truth)))
    if not use.any():
        return float("nan")
    return float(np.mean(np.clip((out[use] - truth[use]) / change[use], -1.0, 1.0)))


@dataclass
class CaseScores:
    """Per frame (index 0 = frame 1) and region, PU21-PSNR (dB) of each output, and the ghost residue."""

    pu21: dict[tuple[str, str], list[float]]  # (output, region) -> per frame
    ghost: dict[str, list[float]]  # output -> per frame


def region_masks(motions: list[np.ndarray], i: int) -> dict[str, np.ndarray]:
    """The regions of frame ``i`` (0-based) of a rendered sequence: still, moving, trail (see the module)."""
    recent = np.any(motions[max(0, i - TRAIL_FRAMES):i + 1], axis=0)
    moved_before = np.any(motions[max(0, i - TRAIL_FRAMES):i], axis=0) if i > 0 else np.zeros_like(motions[i])
    return {"still": ~recent, "moving": motions[i], "trail": moved_before & ~motions[i]}


def trail_before(motions: list[np.ndarray], truths: list[np.ndarray], i: int) -> np.ndarray:
    """Each pixel's truth in the frame before its last motion within :data:`TRAIL_FRAMES` frames before
    ``i`` (its truth in frame ``i`` where it did not move), float32 (H, W)."""
    before = truths[i].copy()
    for j in range(max(1, i - TRAIL_FRAMES), i):  # later changes overwrite earlier ones
        before = np.where(motions[j], truths[j - 1], before)
    return before


def run_case(scene: Scene, frames: int, pattern: str, sensor: Sensor,
             streams: dict[str, Callable[[list[np.ndarray]], object]],
             single: Callable[[np.ndarray], np.ndarray] | dict[str, Callable[[np.ndarray], np.ndarray]],
             pu21: Callable[[np.ndarray, np.ndarray, np.ndarray], float], seed: int = 1) -> CaseScores:
    """Render ``frames`` frames of ``scene`` with ``sensor`` and score each stream and the single frame.

    Args:
        streams: name -> a factory of a fresh stream (``process(raw).image``), called with the rendered raw
            frames (uint16 (H, W) each; a stream given a model estimated from the first frames reads them).
        single: raw uint16 (H, W) -> the single-frame default's image, scored as ``"single"``; or several,
            name -> that function (e.g. the default with the stream's model given, to tell the fusion's
            effect from the method's response to its noise model).
        pu21: (image, truth, region) -> PU21-PSNR (dB) over the region, display scaling from the whole truth.
    """
    rendered = list(render_sequence(scene, frames, pattern, sensor, seed=seed))
    truths = [f.truth for f in rendered]
    motions = [f.motion for f in rendered]
    made = {name: factory([f.raw for f in rendered]) for name, factory in streams.items()}
    scores = CaseScores({}, {})
    for i, f in enumerate(rendered):
        images = {name: one(f.raw) for name, one in (single.items() if isinstance(single, dict)
                                                      else [("single", single)])}
        images.update({name: stream.process(f.raw).image for name, stream in made.items()})
        regions = region_masks(motions, i)
        before = trail_before(motions, truths, i)
        for name, image in images.items():
            for region, mask in regions.items():
                scores.pu21.setdefault((name, region), []).append(pu21(image, f.truth, mask) if mask.any()
                                                                   else float("nan"))
            scores.ghost.setdefault(name, []).append(ghost_residue(image, f.truth, before, regions["trail"]))
    return scores


# ----- the stability suite's stream cases (svelive.bench.sweep.Sweep; wired in by the suite) ---------

#: object speeds (px per frame) and light (stops under full scale) of :func:`stream_sweeps`
SWEEP_SPEEDS: tuple[float, ...] = (2.0, 6.0, 12.0, 24.0)
SWEEP_STOPS: tuple[float, ...] = (2.0, 4.0, 6.0)
SWEEP_FRAMES = 6


def _pu21(image: np.ndarray, truth: np.ndarray, region: np.ndarray) -> float:
    """PU21-PSNR (dB) over ``region``, display scaling from the whole truth (nan for an empty region)."""
    from svelive.metrics import PU21_PEAK, display_scale, pu21_encode

    if not region.any():
        return float("nan")
    s = display_scale(truth)
    err = pu21_encode(image[region] * s) - pu21_encode(truth[region] * s)
    return float(10 * np.log10(PU21_PEAK ** 2 / max(float(np.mean(err * err)), 1e-12)))


def stream_sweeps(size: int = 96, pattern: str = "1,4/16,64", seed: int = 11) -> list:
    """The library stream against the single-frame default, as stability sweeps (lower is better):

    - ``stream_moving``: PU21 dB the stream loses on moving pixels (frames 2 on) against the single frame, a
      textured object (a disc of the mttamwest crop, 3 stops over the scene) crossing the dim desk crop (5 stops
      under) at each speed; ``README`` (no model given) against ``svelive.reconstruct``, ``same model``: both
      given the true one (the fusion's own effect);
    - ``stream_trail``: the ghost residue of the same runs, the stream's minus the single frame's (% of the change);
    - ``stream_still``: PU21 dB the stream is below the single frame on still pixels at its last frame, the still
      desk crop at each light (negative: the fusion's gain).

    The true sensor (3 000 e-, 2 e-, black 64) is not given to the README stream. About 10 s at 96 px.
    """
    import svelive
    from svelive.scenes import static
    from svelive.simulation import load_sample_scene

    levels = dict(black_level=64, white_level=4095)
    sensor = Sensor.from_full_well(12, 3_000, 2.0, **levels)
    true = dict(gain=sensor.gain, read_noise=sensor.read_noise)
    streams = {"README": lambda raws: svelive.Reconstructor(pattern, **levels),
               "same model": lambda raws: svelive.Reconstructor(pattern, **levels, **true)}
    singles = {"README": lambda raw: svelive.reconstruct(raw, pattern, **levels),
               "same model": lambda raw: svelive.reconstruct(raw, pattern, **levels, **true)}
    desk = np.maximum(load_sample_scene("desk"), 0)
    h, w = desk.shape
    scene = desk[(h - size) // 2:][:size, (w - size) // 2:][:, :size]
    texture = np.maximum(load_sample_scene("mttamwest"), 0)[:size, :size]
    moving = Sweep("stream_moving", "Library stream: moving pixels against the single frame", "object speed (px/frame)",
                   "PU21 dB lost on moving pixels", list(SWEEP_SPEEDS), log_y=False,
                   notes="a textured disc over the dim desk crop; 'same model': stream and single frame given the "
                         "true noise model, the fusion's own effect")
    trail = Sweep("stream_trail", "Library stream: trail behind a moving object", "object speed (px/frame)",
                  "ghost residue, stream minus single (% of the change)", list(SWEEP_SPEEDS), log_y=False,
                  notes="share of a pixel's change its output still shows, over pixels moved in the last 3 frames")
    still = Sweep("stream_still", "Library stream: still scene against the single frame", "stops under full scale",
                  f"PU21 dB below the single frame at frame {SWEEP_FRAMES}", list(SWEEP_STOPS), log_y=False,
                  notes="negative: the fusion's gain")
    background = dim(scene, pattern, sensor, 5.0)
    texture = texture * (8 * float(np.percentile(background, 99.9)) / max(float(np.percentile(texture, 99.9)), 1e-12))
    radius = size / 7
    for speed in SWEEP_SPEEDS:
        crossing = moving_texture(background, texture, radius, (size / 2, radius + 2), (0.0, speed))
        for name in streams:
            scores = run_case(crossing, SWEEP_FRAMES, pattern, sensor, {name: streams[name]}, singles[name], _pu21,
                              seed=seed)
            lost = np.array(scores.pu21[("single", "moving")][1:]) - np.array(scores.pu21[(name, "moving")][1:])
            moving.errors.setdefault(name, []).append(float(np.nanmean(lost)))
            ghost = np.nanmean(scores.ghost[name][1:]) - np.nanmean(scores.ghost["single"][1:])
            trail.errors.setdefault(name, []).append(100 * float(ghost))
    for stops in SWEEP_STOPS:
        for name in streams:
            scores = run_case(static(dim(scene, pattern, sensor, stops)), SWEEP_FRAMES, pattern, sensor,
                              {name: streams[name]}, singles[name], _pu21, seed=seed)
            still.errors.setdefault(name, []).append(scores.pu21[("single", "still")][-1]
                                                     - scores.pu21[(name, "still")][-1])
    return [moving, trail, still]
