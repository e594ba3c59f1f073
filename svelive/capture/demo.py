"""``demo``: a synthetic live SVE camera, so everything runs on a machine without one.

The scene is a real HDR photograph shipped in ``svelive/data`` (BSD licence): by
default ``mttamwest-wide``, a 968x548 RGB crop of MtTamWest.exr, rendered at its
native resolution (960x540: the crop less a 4-pixel margin on each side for the
camera's motion). Another frame size sees the same field of view, the scene
resampled once at open (area averaging down, bilinear up). The camera pans
gently along an ellipse within the margin by sub-pixel shifts (bilinear), and a
bright Gaussian light moves across the frame (its peak at 0.8 of the shortest
exposure's range, so it saturates the longer ones: the HDR case). Each frame is
rendered through the colour filter, the exposure pattern and the sensor noise
model, and delivered at ``fps``.

Colour (``cfa``): ``RGGB`` by default, with the dual-ISO layout's exposures
``1/1/8/8`` (row pairs at two gains, so every Bayer phase sees both exposures in
each 4x2 tile; the mono pattern ``1,4/16,64`` on a 2x2 Bayer cell would give red
only exposure 1 and blue only 64). The scene's linear Rec.709 RGB stands for the
camera's RGB. Frames are labelled with the Bayer format of the filter
(``BayerRG12``); a filter without a PFNC name (``quad-RGGB``) gets ``Mono12``.
``cfa="none"`` is the monochrome demo: the scene's luminance, pattern
``1,4/16,64``, ``Mono12``. ``pixel_format`` (e.g. ``BayerGR12``, ``BayerRG16``,
``Mono16``) makes the demo behave like a camera delivering that format: the
label and bit depth are the format's, the colour filter is the one its name
gives, and a contradicting ``cfa`` is refused (:func:`source.resolve_cfa`).

Noise: ``exact=True`` renders with :func:`svelive.simulation.simulate`
(Poisson-Gaussian, colour through ``cfa``; slow). The default renders the same model's Gaussian
approximation (mean ``e L``, variance ``Sensor.signal_variance``) in one
compiled pass (shift, light, colour filter, exposure, noise, rounding); the
standard normal deviates come from a bank of twice the frame's size drawn once,
read from a random start each frame (with a random sign), so a pixel sees a
different deviate in every frame.

Exposure time (``exposure_us``, microseconds, default :data:`REFERENCE_EXPOSURE_US`): the
light collected scales with it, so a frame at 15 000 us is rendered from 1.5 times the
radiance of one at 10 000 us (the scene's fill above is for the reference time), with the
noise of that signal. :meth:`DemoSource.set_exposure_time` changes it from the next frame
rendered on, within :data:`EXPOSURE_RANGE_US`, as ``ExposureTime`` does on a GigE camera, so
``svelive serve --source demo`` can show the live exposure sweep (``POST
/api/calibrate/response {"sweep": [...]}``). The sweep compares frames taken at different
moments, so it wants a still scene: ``period_s=0`` stops the pan and the moving light.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from svelive.capture import build_sensor, make_config
from svelive.capture.source import MONO_WORDS, EndOfStream, Source
from svelive.core import formats
from svelive.core.camera import COLOUR_LAYOUTS
from svelive.core.errors import SveliveError
from svelive.core.frame import Frame
from svelive.core.sensor import Sensor
from svelive.exr import LUMA_WEIGHTS, read_rgb
from svelive.jit import kernel

#: The demo's own scene (RGB, native resolution) by name; the 256x256 sample crops are accepted too.
DEMO_SCENES = {"mttamwest-wide": "mttamwest-wide.exr"}
#: Pixels of the scene kept on each side of the frame for the camera's motion (at native resolution).
MARGIN = 4
DEFAULT_CFA = "RGGB"
#: Exposures of the colour demo (the dual-ISO layout) and of the monochrome one.
COLOUR_PATTERN = COLOUR_LAYOUTS["dual-iso"][0]
MONO_PATTERN = "1,4/16,64"
#: Relative RGB of the moving light (warm white); its brightest channel peaks at LIGHT_PEAK.
LIGHT_RGB = (1.0, 0.86, 0.7)
#: Light peak as a fraction of the shortest exposure's range.
LIGHT_PEAK = 0.8
#: Light profile values below this fraction of the peak are zero (no denormals; far below 1 DN).
LIGHT_FLOOR = 1e-12
#: Exposure time (microseconds) at which the scene fills the sensor as described; others scale the light.
REFERENCE_EXPOSURE_US = 10_000.0
#: Exposure times the demo accepts, microseconds (a GigE camera's typical range).
EXPOSURE_RANGE_US = (10.0, 1_000_000.0)
#: Largest demo frame: 8K UHD. The demo holds about 40 bytes per pixel (scene planes, noise bank,
#: exposure and channel maps), so this is ~1.3 GB; a larger request is refused, not attempted.
MAX_SIZE = (7680, 4320)


@dataclass(frozen=True)
class DemoConfig:
    """Options of the demo source.

    Attributes:
        width, height: frame size in pixels; None: the scene's native size (one given: the
            other from the scene's aspect ratio).
        fps: frame rate (frames per second); 0 renders as fast as possible.
        scene: ``mttamwest-wide`` or a 256x256 sample scene (see svelive.simulation.SAMPLE_SCENES).
        period_s: seconds for one full pan ellipse (and one pass of the light); 0: a still scene.
        exposure_us: exposure time in microseconds (REFERENCE_EXPOSURE_US fills the sensor
            as described above; the light collected scales with it).
        exact: render with the exact Poisson-Gaussian simulator (slow).
        frames: stop after this many frames (None: endless).
        seed: noise seed.
        pixel_format: label the frames with this format and take the bit depth and colour
            filter from it, as a camera would (None: from ``cfa`` and the bit depth).
    """

    width: int | None = None
    height: int | None = None
    fps: float = 30.0
    scene: str = "mttamwest-wide"
    period_s: float = 20.0
    exposure_us: float = REFERENCE_EXPOSURE_US
    exact: bool = False
    frames: int | None = None
    seed: int = 0
    pixel_format: str | None = None


def scene_names() -> list[str]:
    """The scene names the demo accepts."""
    from svelive.simulation import SAMPLE_SCENES

    return [*DEMO_SCENES, *SAMPLE_SCENES]


def load_scene_rgb(name: str) -> np.ndarray:
    """A shipped scene's linear RGB, float32 (H, W, 3), non-negative and finite, relative units."""
    from svelive.simulation import sample_scene_path

    if name in DEMO_SCENES:
        path = Path(str(resources.files("svelive") / "data" / DEMO_SCENES[name]))
    elif name in scene_names():
        path = sample_scene_path(name)
    else:
        raise SveliveError(f"demo: unknown scene {name!r}; choose from {', '.join(scene_names())}")
    rgb = read_rgb(path).astype(np.float32)
    return np.clip(np.nan_to_num(rgb, nan=0.0, posinf=0.0, neginf=0.0), 0, None)


def cover(scene: np.ndarray, width: int, height: int, margin: int = MARGIN) -> np.ndarray:
    """``scene`` (H, W, C) resampled once so that its part within ``margin`` covers ``width`` x ``height``.

    At the native size (the scene less the margins) it is returned as it is; otherwise
    scaled by one factor for both axes (area averaging down, bilinear up: neither
    overshoots at HDR edges), with at least two pixels to spare on each axis for the
    bilinear shifts.
    """
    h0, w0 = scene.shape[:2]
    s = max(width / max(w0 - 2 * margin, 1), height / max(h0 - 2 * margin, 1))
    if s == 1.0:
        return scene
    size = (max(int(round(w0 * s)), width + 2), max(int(round(h0 * s)), height + 2))
    out = cv2.resize(scene, size, interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
    return out.reshape(size[1], size[0], scene.shape[2])


def light_profile(n: int, centre: float, sigma: float) -> np.ndarray:
    """Gaussian profile along one axis, float32 (n,), 1 at ``centre``; values below LIGHT_FLOOR are 0.

    The light is the outer product of two such profiles over the whole frame: no
    window whose edge would show (a light cut off at 4 sigma left a square of
    exp(-8) = 3e-4 of the peak, about 70 DN at exposure 64, on dark ground).
    """
    p = np.exp(-((np.arange(n, dtype=np.float64) - centre) ** 2) / (2 * sigma * sigma))
    p[p < LIGHT_FLOOR] = 0.0
    return p.astype(np.float32)


def check_size(width: int | None, height: int | None) -> None:
    """Refuse (one line) a demo frame larger than :data:`MAX_SIZE` in pixels or on either side."""
    w, h = (v or 0 for v in (width, height))
    most = MAX_SIZE[0] * MAX_SIZE[1]
    if w * h > most or max(w, h) > MAX_SIZE[0]:
        size = f"{w}x{h}" if w and h else f"width {w}" if w else f"height {h}"
        raise SveliveError(f"demo: {size} is larger than the demo renders (at most {MAX_SIZE[0]} pixels "
                           f"a side and {MAX_SIZE[0]}x{MAX_SIZE[1]} = {most / 1e6:.1f} MP); give a smaller --width/--height")


class DemoSource(Source):
    """The synthetic SVE camera; see the module docstring."""

    def __init__(self, spec: str, arg: str | None = None, *, pattern: str | None = None,
                 sensor: Sensor | None = None, bits: int | None = None, black_level: float | None = None,
                 white_level: float | None = None, cfa: str | None = None, **opts: Any) -> None:
        if arg:
            opts.setdefault("scene", arg)
        self.config: DemoConfig = make_config(DemoConfig, opts, spec)
        c = self.config
        if c.fps < 0 or any(v is not None and v < 16 for v in (c.width, c.height)):
            raise SveliveError(f"demo: need width, height >= 16 and fps >= 0, got {c.width}x{c.height} @ {c.fps}")
        if c.period_s < 0 or not math.isfinite(c.period_s):
            raise SveliveError(f"demo: period_s must be >= 0 (0: a still scene), got {c.period_s}")
        self._exposure_us = self._check_exposure(c.exposure_us)
        self._pattern_exposure: np.ndarray | None = None  # the pattern's exposure map, once open
        check_size(c.width, c.height)
        if c.scene not in scene_names():
            raise SveliveError(f"demo: unknown scene {c.scene!r}; choose from {', '.join(scene_names())}")
        fmt = formats.lookup(c.pixel_format) if c.pixel_format else None
        layout = isinstance(pattern, str) and pattern.strip() in COLOUR_LAYOUTS
        if cfa is None and fmt is None and not layout:
            cfa = DEFAULT_CFA
        mono = isinstance(cfa, str) and cfa.strip().lower() in MONO_WORDS
        colour = not mono and (cfa is not None or layout or (fmt is not None and fmt.cfa is not None))
        super().__init__(spec, pattern=pattern or (COLOUR_PATTERN if colour else MONO_PATTERN), cfa=cfa,
                         sensor=build_sensor(sensor, bits, black_level, white_level,
                                             default_bits=12 if fmt is None else fmt.bits))
        # as a camera would: the format's colour filter, reconciled with the one asked for
        self._settle_camera(self.sensor, None if fmt is None else fmt.cfa, None if fmt is None else fmt.name)
        self._label = fmt.name if fmt is not None else formats.unpacked_name(self.sensor.bits, self.camera.cfa)

    def _open(self) -> None:
        from svelive.simulation import exposure_scale

        c = self.config
        rgb = load_scene_rgb(c.scene)
        if self.camera.cfa is None:
            rgb = (rgb @ np.asarray(LUMA_WEIGHTS, np.float32))[:, :, None]
        h0, w0 = rgb.shape[:2]
        width = c.width or (round((w0 - 2 * MARGIN) * c.height / (h0 - 2 * MARGIN)) if c.height else w0 - 2 * MARGIN)
        height = c.height or round((h0 - 2 * MARGIN) * width / (w0 - 2 * MARGIN))
        self.size = (int(width), int(height))
        check_size(*self.size)
        pattern, sensor = self.camera.require_pattern(), self.sensor
        scene = cover(rgb, *self.size)
        scene = scene * np.float32(exposure_scale(scene.max(axis=2), pattern, sensor, stops_below_fill=1.0))
        self._planes = np.ascontiguousarray(scene.transpose(2, 0, 1), dtype=np.float32)  # (C, H', W')
        # the pan: offsets of the frame's top-left pixel in the scene, within what bilinear sampling allows
        self._span = ((scene.shape[1] - width - 1) / 2.0, (scene.shape[0] - height - 1) / 2.0)
        peak = LIGHT_PEAK * sensor.range_dn / float(pattern.levels[0])
        tint = LIGHT_RGB if scene.shape[2] == 3 else (1.0,)
        self._light = (peak * np.asarray(tint, np.float64) / max(tint)).astype(np.float32)
        cfa = self.camera.cfa
        self._channels = np.zeros((height, width), np.uint8) if cfa is None else cfa.channel_map((height, width))
        # per row of the filter's tile and channel: 1 where the row's pixels see that channel
        rows = self._channels[: 1 if cfa is None else min(cfa.shape[0], height)]
        self._masks = np.stack([rows == ch for ch in range(scene.shape[2])], axis=1).astype(np.float32)
        self._present = np.ascontiguousarray(self._masks.any(axis=2))
        self._pattern_exposure = np.ascontiguousarray(pattern.exposure_map((height, width)), dtype=np.float32)
        self._exposure = self._scaled_exposure(self._exposure_us)
        self._rng = np.random.default_rng(c.seed)
        self._noise = self._rng.standard_normal(max(2 * width * height, 1 << 16), dtype=np.float32)
        self._dtype = np.uint8 if sensor.bits <= 8 else np.uint16
        _render_kernel(*self._kernel_args(0.0, np.zeros((2, 2), self._dtype)))  # compile or load it now
        self._n = 0
        self._t0 = time.monotonic()

    # ----- exposure control ------------------------------------------------
    @staticmethod
    def _check_exposure(value: float) -> float:
        lo, hi = EXPOSURE_RANGE_US
        if not (math.isfinite(value) and lo <= value <= hi):
            raise SveliveError(f"demo: exposure time {value:g} us is outside the demo's range {lo:g}..{hi:g} us")
        return float(value)

    def _scaled_exposure(self, exposure_us: float) -> np.ndarray:
        """The pattern's exposure map times exposure_us / REFERENCE_EXPOSURE_US, float32 (H, W)."""
        assert self._pattern_exposure is not None
        scale = exposure_us / REFERENCE_EXPOSURE_US
        if scale == 1.0:
            return self._pattern_exposure
        return np.ascontiguousarray(self._pattern_exposure * np.float32(scale))

    def exposure_time(self) -> float | None:
        """The exposure time in microseconds."""
        return self._exposure_us

    def set_exposure_time(self, value: float) -> float:
        """Set the exposure time (microseconds, within EXPOSURE_RANGE_US) from the next frame on;
        returns it."""
        value = self._check_exposure(float(value))
        if self._pattern_exposure is not None:  # open: the map the next frame is rendered with
            self._exposure = self._scaled_exposure(value)
        self._exposure_us = value
        return value

    def _geometry(self, t: float) -> tuple[int, int, float, float, np.ndarray, np.ndarray]:
        """At time ``t`` s: the integer and fractional offsets (rows, cols) of the frame in the scene,
        and the light's row and column profiles."""
        c = self.config
        width, height = self.size
        phase = 2 * math.pi * t / c.period_s if c.period_s else 0.0
        dx = self._span[0] * (1 - math.cos(phase))
        dy = self._span[1] * (1 - math.cos(2 * phase)) / 2 + self._span[1] / 2
        oy, ox = int(math.floor(dy)), int(math.floor(dx))
        # the light crosses the frame on a Lissajous path
        cx = width * (0.5 + 0.35 * math.sin(2.3 * phase))
        cy = height * (0.5 + 0.3 * math.sin(3.1 * phase + 0.7))
        r = 0.04 * min(width, height)
        return oy, ox, dy - oy, dx - ox, light_profile(height, cy, r), light_profile(width, cx, r)

    def radiance(self, t: float) -> np.ndarray:
        """The scene the sensor sees at time ``t`` seconds, in DN at exposure 1: float32 (height, width)
        for the monochrome demo, (height, width, 3) linear RGB with a colour filter."""
        width, height = self.size
        oy, ox, fy, fx, ly, lx = self._geometry(t)
        s = self._planes.transpose(1, 2, 0)[oy:oy + height + 1, ox:ox + width + 1]
        fy, fx = np.float32(fy), np.float32(fx)
        top = s[:-1, :-1] * (1 - fx) + s[:-1, 1:] * fx
        bottom = s[1:, :-1] * (1 - fx) + s[1:, 1:] * fx
        img = top * (1 - fy) + bottom * fy
        img += (ly[:, None] * lx[None, :])[:, :, None] * self._light
        return img[:, :, 0] if self.camera.cfa is None else img

    def mosaic(self, t: float) -> np.ndarray:
        """The radiance each pixel's filter passes at time ``t``: float32 (height, width), DN at exposure 1."""
        img = self.radiance(t)
        if img.ndim == 2:
            return img
        return np.take_along_axis(img, self._channels[:, :, None].astype(np.intp), axis=2)[:, :, 0]

    def _kernel_args(self, t: float, out: np.ndarray) -> tuple:
        oy, ox, fy, fx, ly, lx = self._geometry(t)
        s = self.sensor
        masks, exposure = self._masks, self._exposure
        if out.shape != exposure.shape:  # the compile-time call on a tiny frame (same array layouts)
            h, w = out.shape
            ly, lx = ly[:h], lx[:w]
            masks, exposure = np.ascontiguousarray(masks[..., :w]), np.ascontiguousarray(exposure[:h, :w])
        start = int(self._rng.integers(0, self._noise.size - out.size + 1))
        sign = 1.0 if self._rng.random() < 0.5 else -1.0
        return (self._planes, oy, ox, fy, fx, ly, lx, self._light, masks, self._present, exposure, self._noise,
                start, sign, 1.0 / s.effective_gain, s.floor_variance, s.black_level, s.white_level, out,
                np.empty(out.shape[1], np.float32))

    def _render(self, t: float) -> np.ndarray:
        if self.config.exact:
            from svelive.simulation import simulate

            scale = np.float32(self._exposure_us / REFERENCE_EXPOSURE_US)
            return simulate(self.radiance(t) * scale, self.camera.require_pattern(), self.sensor,
                            cfa=self.camera.cfa, seed=self._rng).raw
        out = np.empty(self._channels.shape, self._dtype)
        _render_kernel(*self._kernel_args(t, out))
        return out

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
                      device_time_ns=int(round(scene_t * 1e9)), pixel_format=self._label, camera=self.camera,
                      exposure_time=self._exposure_us)
        self._n += 1
        return frame

    def _extra_stats(self) -> dict[str, Any]:
        c = self.config
        return {"scene": c.scene, "pattern": self.pattern, "target_fps": c.fps, "exposure_us": self._exposure_us}


@kernel
def _render_kernel(planes: np.ndarray, oy: int, ox: int, fy: float, fx: float, ly: np.ndarray, lx: np.ndarray,
                   light: np.ndarray, masks: np.ndarray, present: np.ndarray, exposure: np.ndarray,
                   noise: np.ndarray, start: int, sign: float, inv_gain: float, floor_variance: float,
                   black: float, white: float, out: np.ndarray, row: np.ndarray) -> None:
    """One raw frame, row by row.

    The scene ``planes`` float32 (C, H', W') shifted by (oy + fy, ox + fx) pixels (bilinear),
    plus the light ``light[c] ly[y] lx[x]``, is summed over the channels weighted by the
    filter's ``masks`` float32 (th, C, W) of row ``y % th`` (``present`` (th, C): which
    channels the row has at all) into ``row`` (W,); times the exposure map, that is the
    signal s in DN. Gaussian noise of variance ``s inv_gain + floor_variance`` from
    ``noise[start:]`` times ``sign``, plus black, rounded and clipped to [0, white], goes
    into ``out`` (H, W). Every inner loop runs over contiguous rows, so it vectorises
    (a per-pixel channel gather does not: three times slower).
    """
    h, w = out.shape
    th = masks.shape[0]
    fy32, fx32 = np.float32(fy), np.float32(fx)
    w00, w01 = (np.float32(1) - fy32) * (np.float32(1) - fx32), (np.float32(1) - fy32) * fx32
    w10, w11 = fy32 * (np.float32(1) - fx32), fy32 * fx32
    inv_gain32, floor32, sign32 = np.float32(inv_gain), np.float32(floor_variance), np.float32(sign)
    offset32, top32, zero = np.float32(black) + np.float32(0.5), np.float32(white) + np.float32(0.5), np.float32(0)
    for y in range(h):
        phase = y % th
        for x in range(w):
            row[x] = zero
        for c in range(planes.shape[0]):
            if not present[phase, c]:
                continue
            m = masks[phase, c]
            r0 = planes[c, oy + y, ox:]
            r1 = planes[c, oy + y + 1, ox:]
            lc = light[c] * ly[y]
            for x in range(w):
                row[x] += m[x] * (r0[x] * w00 + r0[x + 1] * w01 + r1[x] * w10 + r1[x + 1] * w11 + lc * lx[x])
        e = exposure[y]
        o = out[y]
        k = start + y * w
        for x in range(w):
            signal = row[x] * e[x]
            value = signal + np.sqrt(signal * inv_gain32 + floor32) * noise[k + x] * sign32 + offset32
            o[x] = np.uint16(min(max(value, zero), top32))  # value + 0.5 truncated: rounded
