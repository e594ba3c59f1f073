"""Moving-scene simulator: raw SVE sequences with sub-frame time sampling, ground truth and motion masks.

A scene is a function ``scene(t) -> radiance`` (float32 (H, W), DN at exposure
1) of continuous time t in frame periods (frame i spans [i, i + 1)). Each
exposure integrates the scene over its own time window, approximated by the
average of ``samples`` instants:

- ``mask`` timing (neutral-density mask, per-pixel gain): every exposure
  integrates over the same window [i, i + duty);
- ``integration`` timing (different integration times): exposure e_k
  integrates over the last duty * e_k / e_max of that window, all ending at
  readout, so long exposures see a longer stretch of any motion.

The ground truth of a frame is the radiance averaged over the shortest
exposure's window (the sharpest record of the frame the sensor has); the
ground-truth motion mask marks pixels whose radiance changes by more than
``motion_threshold`` (relative) within the frame or since the previous frame.

Scenes here take arrays: benchmarks load real HDR images from ../shared/data
(:func:`load_beachball`), tests use the shipped crops or synthetic content.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from svelive.core.errors import SveliveError
from svelive.core.pattern import Pattern
from svelive.core.sensor import Sensor
from svelive.exr import read_exr, read_luminance
from svelive.simulation import simulate

Scene = Callable[[float], np.ndarray]
TIMINGS = ("mask", "integration")


@dataclass(frozen=True)
class MovingFrame:
    """One simulated frame of a moving scene.

    Attributes:
        raw: uint8/uint16 (H, W), raw DN including the black level.
        truth: float32 (H, W), radiance (DN at exposure 1) over the shortest exposure's window.
        motion: bool (H, W), ground-truth motion mask.
    """

    raw: np.ndarray
    truth: np.ndarray
    motion: np.ndarray


def _shift(image: np.ndarray, dy: float, dx: float, shape: tuple[int, int], border: float = 0.0) -> np.ndarray:
    """``image`` translated by (dy, dx) pixels (bilinear) onto a canvas of ``shape``, float32."""
    matrix = np.float32([[1, 0, dx], [0, 1, dy]])
    return cv2.warpAffine(np.asarray(image, np.float32), matrix, (shape[1], shape[0]), flags=cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=float(border))


def panning(image: np.ndarray, shape: tuple[int, int], velocity: tuple[float, float],
            origin: tuple[float, float] = (0.0, 0.0)) -> Scene:
    """A ``shape`` crop of ``image`` whose top-left corner moves from ``origin`` by ``velocity`` (rows, cols per frame).

    The crop must stay inside the image over the frames rendered (beyond it the scene is 0).
    """
    image = np.asarray(image, np.float32)

    def scene(t: float) -> np.ndarray:
        return _shift(image, -(origin[0] + velocity[0] * t), -(origin[1] + velocity[1] * t), shape)

    return scene


def static(image: np.ndarray) -> Scene:
    """A scene that never changes."""
    image = np.asarray(image, np.float32)
    return lambda t: image


def moving_disc(background: np.ndarray, radiance: float, radius: float, start: tuple[float, float],
                velocity: tuple[float, float]) -> Scene:
    """An anti-aliased disc of ``radiance`` moving over ``background`` from ``start`` (centre, rows/cols) by ``velocity``."""
    background = np.asarray(background, np.float32)
    yy, xx = np.mgrid[0:background.shape[0], 0:background.shape[1]].astype(np.float32)

    def scene(t: float) -> np.ndarray:
        cy, cx = start[0] + velocity[0] * t, start[1] + velocity[1] * t
        cover = np.clip(radius + 0.5 - np.hypot(yy - cy, xx - cx), 0, 1)
        return background + cover * (np.float32(radiance) - background)

    return scene


def modulated(scene: Scene, gain: Callable[[float], float]) -> Scene:
    """``scene`` with its brightness multiplied by ``gain(t)`` (illumination jumps, flicker)."""
    return lambda t: scene(t) * np.float32(gain(t))


def mains_flicker(fps: float, mains_hz: float = 50.0, depth: float = 0.3) -> Callable[[float], float]:
    """Brightness of lamps on ``mains_hz`` AC (intensity at twice that), t in frames of ``fps``."""
    return lambda t: 1.0 + depth * np.sin(2 * np.pi * 2 * mains_hz * t / fps)


def placed_frames(frames: list[tuple[np.ndarray, tuple[int, int]]], shape: tuple[int, int],
                  background: float = 0.0) -> Scene:
    """Images placed at their (row, col) origins on a ``shape`` canvas, one per frame.

    Between integer times the image of frame floor(t) moves linearly towards the
    next frame's origin, so sub-frame sampling sees the motion.
    """
    if not frames:
        raise SveliveError("placed_frames needs at least one frame")

    def scene(t: float) -> np.ndarray:
        i = int(np.clip(np.floor(t), 0, len(frames) - 1))
        image, (y0, x0) = frames[i]
        y1, x1 = frames[min(i + 1, len(frames) - 1)][1]
        f = float(np.clip(t - i, 0, 1))
        return _shift(image, y0 + f * (y1 - y0), x0 + f * (x1 - x0), shape, background)

    return scene


def load_beachball(directory: str | Path, scale: float = 0.5) -> tuple[list[tuple[np.ndarray, tuple[int, int]]], tuple[int, int]]:
    """The Beachball frames (luminance) with their data-window origins, and the display-window shape, resized by ``scale``."""
    files = sorted(Path(directory).glob("*.exr"))
    if not files:
        raise SveliveError(f"no EXR files in {directory}")
    frames = []
    shape = None
    for path in files:
        _, header = read_exr(path)
        (x0, y0), _ = header["dataWindow"]
        (dx0, dy0), (dx1, dy1) = header["displayWindow"]
        shape = (int(round((dy1 - dy0 + 1) * scale)), int(round((dx1 - dx0 + 1) * scale)))
        luminance = np.maximum(read_luminance(path), 0)
        small = cv2.resize(luminance, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        frames.append((small, (int(round((y0 - dy0) * scale)), int(round((x0 - dx0) * scale)))))
    return frames, shape


def render_sequence(scene: Scene, n_frames: int, pattern: Pattern | str, sensor: Sensor, *, timing: str = "mask",
                    samples: int = 8, duty: float = 1.0, seed: int = 0,
                    motion_threshold: float = 0.05) -> Iterator[MovingFrame]:
    """Render ``n_frames`` raw SVE frames of a moving scene (see the module docstring).

    Args:
        scene: radiance (DN at exposure 1) as a function of time in frames.
        timing: ``"mask"`` or ``"integration"``.
        samples: instants per frame over the longest exposure's window.
        duty: fraction of the frame period the longest exposure integrates.
        seed: noise seed of the first frame (frame i uses seed + i).
        motion_threshold: relative radiance change that counts as motion in the
            ground-truth mask (changes below 1e-3 of the frame's 99.9th percentile are ignored).
    """
    if timing not in TIMINGS:
        raise SveliveError(f"timing must be one of {', '.join(TIMINGS)}, got {timing!r}")
    if samples < 1 or not 0 < duty <= 1:
        raise SveliveError(f"need samples >= 1 and 0 < duty <= 1, got {samples}, {duty}")
    pattern = Pattern.parse(pattern)
    levels = pattern.levels
    fraction = levels / levels[-1] if timing == "integration" else np.ones_like(levels)
    offsets = duty * (np.arange(samples) + 0.5) / samples
    previous = None
    for i in range(n_frames):
        instants = [np.asarray(scene(i + o), np.float32) for o in offsets]
        shape = instants[0].shape
        index = pattern.level_index_map(shape)
        radiance = np.empty(shape, np.float32)
        truth = None
        for k, f in enumerate(fraction):
            inside = [x for o, x in zip(offsets, instants) if o >= duty * (1 - f)] or instants[-1:]
            mean = np.mean(inside, axis=0)
            radiance[index == k] = mean[index == k]
            if k == 0:
                truth, window = mean, inside
        floor = 1e-3 * max(float(np.percentile(truth, 99.9)), 1e-12)
        motion = np.zeros(shape, bool)
        for x in instants if timing == "integration" else window:
            motion |= np.abs(x - truth) > motion_threshold * np.maximum(truth, floor)
        if previous is not None:
            motion |= np.abs(truth - previous) > motion_threshold * np.maximum(truth, floor)
        previous = truth
        frame = simulate(radiance, pattern, sensor, seed=seed + i)
        yield MovingFrame(frame.raw, truth.astype(np.float32), motion)
