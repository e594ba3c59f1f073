"""What the noise estimators read of a camera and a frame: the signal above black and the lowest value a reading
can take, the level from which it may be clipped, the joint tile's exposures and colours, the given parts of the
model (held fixed in every fit), and the strided blocks of tiles that samples are taken in."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from svelive.core.errors import SveliveError
from svelive.core.sensor import Sensor
from svelive.noise.model import QUANTISATION_VARIANCE

if TYPE_CHECKING:  # the Camera is only read here (its pattern, colour filter and sensor)
    from svelive.core.camera import Camera


def _block_lines(first: int, stop: int, period: int, stride: int, side: int) -> np.ndarray:
    """Rows (or columns) of blocks ``side`` tiles wide (odd): centres every ``stride`` tiles, each with the
    tile lines around it; int64 (side B,), grouped by block."""
    half = side // 2
    centres = np.arange(first + half * period, stop - half * period, period * stride)
    return (centres[:, None] + period * np.arange(-half, half + 1)[None, :]).ravel()


def _layout(camera: Camera) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """The joint tile's nominal exposures and channels (ph, pw), and the calibrated per-pixel map or None."""
    pattern = camera.require_pattern()
    period = camera.period
    reps = lambda tile: np.tile(tile, (period[0] // tile.shape[0], period[1] // tile.shape[1]))  # noqa: E731
    tile_e = reps(np.asarray(pattern.tile, np.float64))
    tile_c = None if camera.cfa is None else reps(np.asarray(camera.cfa.tile))
    return tile_e, tile_c, pattern.pixel_map


def _signal_of(raw: np.ndarray, camera: Camera, signal: np.ndarray | None) -> tuple[np.ndarray, float, float]:
    """(array, offset, floor): the linear signal above black is ``array - offset`` (no full-frame copy is
    made); ``floor`` is the lowest signal a reading can take (DN)."""
    sensor = camera.sensor
    raw = camera.check(raw)
    if signal is not None:
        signal = np.asarray(signal)
        if signal.shape != raw.shape:
            raise SveliveError(f"signal has shape {signal.shape} but the raw frame {raw.shape}")
        # a response's linearisation clips at black; raw frames clip at raw 0
        return signal, 0.0, 0.0 if camera.response is not None else -float(sensor.black_level)
    if camera.response is not None:
        raise SveliveError("this camera has a response curve: give the linearised signal "
                           "(signal=svelive.reconstruction.input.prepare(raw, camera).signal)")
    return raw, float(sensor.black_level), -float(sensor.black_level)


def _high_level(sensor: Sensor) -> float:
    """Signal (DN) from which a reading may be clipped at white: two percent below the range."""
    return 0.98 * sensor.range_dn


def _fixed(sensor: Sensor) -> dict:
    """The given parts of the noise model, held fixed in the fit."""
    return {"slope": None if sensor.gain is None else 1.0 / sensor.gain,
            "intercept": None if sensor.read_noise is None else sensor.read_noise**2 + QUANTISATION_VARIANCE}
