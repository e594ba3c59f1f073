"""Input preparation: a raw frame and its camera in, the SveInput every method takes out.

The one place where the camera description is applied to raw values: the
response curve linearises, the black level is removed, the exposure of every
pixel (the pattern's tile or its calibrated per-pixel map) and the censoring of
near-saturated readings are computed, and a colour filter layout gives every
pixel its channel.
"""

from __future__ import annotations

from concurrent.futures import Executor
from dataclasses import replace
from functools import lru_cache

import numpy as np

from svelive.core.camera import Camera, camera_for_raw
from svelive.core.cfa import ColourFilter
from svelive.core.errors import SveliveError
from svelive.core.frame import Frame
from svelive.core.pattern import Pattern
from svelive.core.response import linearise
from svelive.core.sensor import Sensor
from svelive.jit import flat, kernel
from svelive.noise import NoiseEstimate, estimate_from_frame
from svelive.reconstruction.methods.base import SveInput, exposure_maps, map_on, thread_count


@lru_cache(maxsize=8)
def channel_map(cfa: ColourFilter, shape: tuple[int, int]) -> np.ndarray:
    """The CFA's channel of every pixel, uint8 (H, W), read-only, cached per layout and shape."""
    channels = cfa.channel_map(shape)
    channels.setflags(write=False)
    return channels


def as_camera(camera: Camera | Pattern | str, sensor: Sensor | None = None) -> Camera:
    """A Camera, or one built from a pattern (object or text) and a sensor: a convenience for tests and tools."""
    if isinstance(camera, Camera):
        if sensor is not None and sensor != camera.sensor:
            raise SveliveError("give either a Camera or a pattern with a sensor, not a Camera and another sensor")
        return camera
    return Camera.build(camera, sensor=sensor)


def prepare(raw: np.ndarray | Frame, camera: Camera | Pattern | str | None = None,
            sensor: Sensor | None = None, workers: int | Executor = 1) -> SveInput:
    """Check a raw frame and turn it into the SveInput every method takes.

    Args:
        raw: uint8/uint16 (H, W) raw DN, black level included (or float, already
            linear), or a Frame, whose own camera is used when ``camera`` is None.
        camera: the camera description; a pattern (with ``sensor``) stands for a
            monochrome camera with that pattern.
        workers: threads (methods.base.map_on) over which a uint16 frame's signal and censoring are made, in
            pieces of rows (each pixel's values are its own: the result does not depend on it).
    """
    if isinstance(raw, Frame):
        camera = raw.camera if camera is None else camera
        raw = raw.raw
    if camera is None:
        raise SveliveError("no camera description: give the exposure pattern")
    camera = as_camera(camera, sensor)
    pattern = camera.require_pattern()
    sensor = camera.sensor
    raw = camera.check(raw)
    if camera.response is not None:
        raw = linearise(raw, camera.response, sensor)
    exposure, _ = exposure_maps(pattern, raw.shape)
    if raw.dtype == np.uint16:  # the cameras' type: numpy's arithmetic (below) in one compiled pass
        signal, censored = np.empty(raw.shape, np.float32), np.empty(raw.shape, bool)
        raw = np.ascontiguousarray(raw)
        black, censor = np.float32(sensor.black_level), np.float32(sensor.censor_level)
        pieces = 2 * thread_count(workers) if isinstance(workers, Executor) else workers
        cuts = [raw.shape[0] * k // pieces for k in range(pieces + 1)]
        map_on(workers, lambda rows: _signal(*flat(raw[rows], signal[rows], censored[rows]), black, censor),
               [slice(a, b) for a, b in zip(cuts[:-1], cuts[1:]) if b > a])
    else:  # (one kernel type only: the warm-up compiles it, and no other raw type waits for a compile)
        signal = raw.astype(np.float32)
        signal -= np.float32(sensor.black_level)
        censored = signal >= np.float32(sensor.censor_level)
    integral = raw.dtype.kind in "ui" and float(sensor.black_level).is_integer()
    channels = None if camera.cfa is None else channel_map(camera.cfa, raw.shape)
    return SveInput(signal=signal, exposure=exposure, censored=censored, pattern=pattern, sensor=sensor,
                    integral=integral, cfa=camera.cfa, channels=channels)


@kernel
def _signal(raw, signal, censored, black, censor):
    """signal = raw - black in float32, censored = signal >= censor; flat arrays (raw uint16)."""
    for k in range(signal.size):
        value = np.float32(raw[k]) - black
        signal[k] = value
        censored[k] = value >= censor


def with_noise_model(raw: np.ndarray, camera: Camera, inp: SveInput,
                     noise: NoiseEstimate | None = None) -> tuple[Camera, SveInput, NoiseEstimate]:
    """The camera and input with the noise model filled in where the sensor has none.

    Given values are never overridden. When gain or read noise is unknown, ``noise`` (an
    estimate already made) or else :func:`svelive.noise.estimate_from_frame` of this frame supplies it,
    and the censoring, which depends on the noise at white, is recomputed. ``raw`` is the frame
    ``inp`` was prepared from.
    """
    sensor = camera.sensor
    if sensor.gain is not None and sensor.read_noise is not None:
        return camera, inp, NoiseEstimate.given(sensor)
    if noise is None:
        noise = estimate_from_frame(raw, camera, signal=inp.signal if camera.response is not None else None)
    sensor = noise.apply(sensor)
    camera = camera.replace(sensor=sensor)
    return camera, replace(inp, sensor=sensor, censored=inp.signal >= sensor.censor_level), noise


def sensor_for(raw: np.ndarray, black_level: float = 0, white_level: float | None = None,
               gain: float | None = None, read_noise: float | None = None) -> Sensor:
    """The Sensor a raw array implies: bit depth from its dtype unless the white level says more."""
    return camera_for_raw(raw, None, black_level=black_level, white_level=white_level, gain=gain,
                          read_noise=read_noise).sensor
