"""``demo``: a synthetic live SVE camera, so everything runs on a machine without one.

The scene is a shipped real HDR image (``svelive/data``, BSD licence), upscaled
to cover the frame plus a margin, panned slowly along an ellipse, with a bright
Gaussian light moving across it (its peak near the top of the lowest exposure's
range, so it saturates the longer exposures: the HDR case). Each frame is
rendered through the exposure pattern and the sensor noise model and delivered
at ``fps``.

Noise: ``exact=True`` renders with :func:`svelive.simulate.simulate`
(Poisson-Gaussian, about 90 ms for 1280x720 on this machine's cores, so too
slow for 30 fps); the default renders the same model's Gaussian approximation
(mean ``e L``, variance ``Sensor.signal_variance``), about 12 ms a frame.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from svelive.capture import build_sensor, make_config
from svelive.capture.source import EndOfStream, Source
from svelive.errors import SveliveError
from svelive.frame import Frame
from svelive.pattern import Pattern
from svelive.sensor import Sensor


@dataclass(frozen=True)
class DemoConfig:
    """Options of the demo source.

    Attributes:
        width, height: frame size in pixels.
        fps: frame rate (frames per second); 0 renders as fast as possible.
        scene: shipped sample scene name (see svelive.simulate.SAMPLE_SCENES).
        period_s: seconds for one full pan ellipse.
        exact: render with the exact Poisson-Gaussian simulator (slow).
        frames: stop after this many frames (None: endless).
        seed: noise seed.
    """

    width: int = 1280
    height: int = 720
    fps: float = 30.0
    scene: str = "desk"
    period_s: float = 20.0
    exact: bool = False
    frames: int | None = None
    seed: int = 0


DEFAULT_PATTERN = "1,4/16,64"


class DemoSource(Source):
    """The synthetic SVE camera; see the module docstring."""

    def __init__(self, spec: str, arg: str | None = None, *, pattern: str | None = None,
                 sensor: Sensor | None = None, bits: int | None = None, black_level: float | None = None,
                 white_level: float | None = None, **opts: Any) -> None:
        if arg:
            opts.setdefault("scene", arg)
        self.config: DemoConfig = make_config(DemoConfig, opts, spec)
        c = self.config
        if c.width < 16 or c.height < 16 or c.fps < 0:
            raise SveliveError(f"demo: need width, height >= 16 and fps >= 0, got {c.width}x{c.height} @ {c.fps}")
        pattern_obj = Pattern.parse(pattern or DEFAULT_PATTERN)
        super().__init__(spec, pattern=str(pattern_obj),
                         sensor=build_sensor(sensor, bits, black_level, white_level, default_bits=12))
        self._pattern = pattern_obj

    def _open(self) -> None:
        from svelive.simulate import exposure_scale, load_sample_scene

        c = self.config
        scene = load_sample_scene(c.scene)
        scene = np.clip(np.nan_to_num(scene, nan=0.0, posinf=0.0), 0, None).astype(np.float32)
        side = int(math.ceil(max(c.width * 1.2, c.height * 1.2 * scene.shape[1] / scene.shape[0],
                                 scene.shape[1])))
        big_w, big_h = side, int(math.ceil(side * scene.shape[0] / scene.shape[1]))
        self._big = cv2.resize(scene, (big_w, big_h), interpolation=cv2.INTER_LINEAR)
        self._big *= exposure_scale(self._big, self._pattern, self.sensor, stops_below_fill=1.0)
        self._span = ((big_w - c.width) / 2.0, (big_h - c.height) / 2.0)
        self._light_peak = 0.8 * self.sensor.range_dn / float(self._pattern.levels[0])
        yy, xx = np.mgrid[0:c.height, 0:c.width].astype(np.float32)
        self._grid = (xx, yy)
        self._exposure = self._pattern.exposure_map((c.height, c.width))
        self._rng = np.random.default_rng(c.seed)
        self._n = 0
        self._t0 = time.monotonic()

    def radiance(self, t: float) -> np.ndarray:
        """The scene at time ``t`` seconds: float32 (height, width), DN at exposure 1."""
        c = self.config
        phase = 2 * math.pi * t / c.period_s
        dx = self._span[0] * (1 - math.cos(phase))
        dy = self._span[1] * (1 - math.cos(2 * phase)) / 2 + self._span[1] / 2
        m = np.float32([[1, 0, -dx], [0, 1, -dy]])
        img = cv2.warpAffine(self._big, m, (c.width, c.height), flags=cv2.INTER_LINEAR,
                             borderMode=cv2.BORDER_REFLECT)
        # the moving light: a Gaussian spot crossing the frame on a Lissajous path
        cx = c.width * (0.5 + 0.35 * math.sin(2.3 * phase))
        cy = c.height * (0.5 + 0.3 * math.sin(3.1 * phase + 0.7))
        r = 0.04 * min(c.width, c.height)
        x0, x1 = max(0, int(cx - 4 * r)), min(c.width, int(cx + 4 * r) + 1)
        y0, y1 = max(0, int(cy - 4 * r)), min(c.height, int(cy + 4 * r) + 1)
        if x1 > x0 and y1 > y0:
            xx, yy = self._grid
            d2 = (xx[y0:y1, x0:x1] - cx) ** 2 + (yy[y0:y1, x0:x1] - cy) ** 2
            img[y0:y1, x0:x1] += self._light_peak * np.exp(-d2 / (2 * r * r))
        return img

    def _render(self, t: float) -> np.ndarray:
        radiance = self.radiance(t)
        if self.config.exact:
            from svelive.simulate import simulate

            return simulate(radiance, self._pattern, self.sensor, seed=self._rng).raw
        s = self.sensor
        signal = radiance * self._exposure
        noise = self._rng.standard_normal(signal.shape, dtype=np.float32)
        noise *= np.sqrt(s.signal_variance(signal)).astype(np.float32)
        signal += noise
        signal += np.float32(s.black_level)
        np.rint(signal, out=signal)
        np.clip(signal, 0, s.white_level, out=signal)
        return signal.astype(np.uint8 if s.bits <= 8 else np.uint16)

    def _next(self) -> Frame | None:
        c = self.config
        if c.frames is not None and self._n >= c.frames:
            raise EndOfStream
        scene_t = self._n / c.fps if c.fps else time.monotonic() - self._t0
        if c.fps:
            if not self._wait(min(self._t0 + scene_t - time.monotonic(), self.poll_s)):
                return None
            if time.monotonic() < self._t0 + scene_t:
                return None
            late = time.monotonic() - (self._t0 + scene_t)
            if late > 1.0:  # fell far behind (slow machine): restart the clock rather than burst
                self._t0 += late
        raw = self._render(scene_t)
        frame = Frame(raw=raw, frame_id=self._n, host_time_ns=time.monotonic_ns(),
                      device_time_ns=int(round(scene_t * 1e9)),
                      pixel_format=_mono_name(self.sensor.bits),
                      camera=self.camera)
        self._n += 1
        return frame

    def _extra_stats(self) -> dict[str, Any]:
        c = self.config
        return {"scene": c.scene, "pattern": self.pattern, "target_fps": c.fps}


def _mono_name(bits: int) -> str:
    """The narrowest unpacked Mono format holding ``bits``-bit values."""
    return next(f"Mono{b}" for b in (8, 10, 12, 14, 16) if bits <= b)
