"""The stateful per-stream reconstruction: raw SVE frames in, motion-robust HDR frames out.

``Reconstructor(camera or pattern, ...).process(frame or raw)`` runs a
single-frame method (svelive.reconstruction.single; the library's default unless
told otherwise, with temporal fusion too), then the motion tests, which compare a
window mean computed beside the method from the same readings
(svelive.reconstruction.numerics.window_estimate), not the method's estimate:
the within-frame exposure-consistency test (svelive.reconstruction.consistency,
on by default for ``integration`` exposure timing) and the temporal fusion
(svelive.reconstruction.fusion) that cuts noise where the scene is static and
resets a pixel's history the moment it moves.

Colour frames (a camera with a colour filter) take the joint reconstruction
(svelive.reconstruction.colour): the motion tests and the fusion run on its
luminance, a monochrome SVE problem, with its variance and lower bound (each
pixel's own reading, for the detail step, is s / e' with the channel folded
into its exposure); the chroma's shares, at cell resolution, are fused with
the same history weights and resets (a cell takes the largest weight, i.e. the
most recent reset, of the pixels its chroma reads: its own and its neighbour
cells'), so a moving pixel restarts all its channels together; so is the
chroma's coarse luminance. The fused luminance is refined against the fused
coarse one with the fused variances (svelive.reconstruction.colour.refinement: a
history lowers the noise, so fewer pixels fall back to the coarse estimate
than in one frame), and the output is that luminance times the fused shares.
"""

from __future__ import annotations

import threading
import time
import weakref
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Executor, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from functools import cached_property, lru_cache

import cv2
import numpy as np

from svelive.core.camera import Camera, camera_for_raw
from svelive.core.cfa import ColourFilter, joint_period
from svelive.core.errors import SveliveError
from svelive.core.frame import Frame
from svelive.core.pattern import Pattern
from svelive.core.sensor import Sensor
from svelive.jit import kernel
from svelive.noise import NoiseEstimate, NoiseSchedule, StreamNoise
from svelive.reconstruction import colour, settle
from svelive.reconstruction.colour.interpolate import _pieces
from svelive.reconstruction.config import MotionConfig
from svelive.reconstruction.consistency import Inconsistency, exposure_consistency
from svelive.reconstruction.fusion import (COUNTED_STEP, FUSE_ROWS, RATIO_TOLERANCE, FrameEstimate, Fused,
                                          LuminanceNoise, OutputVariance, ShareError, TemporalState, cell_means, fuse,
                                          noise_evidence)
from svelive.reconstruction.input import prepare
from svelive.reconstruction.methods import DEFAULT_METHOD, METHODS
from svelive.reconstruction.methods.adaptive import _shares_window, noise_model
from svelive.reconstruction.methods.base import (Estimate, SveInput, exposure_maps, map_on, support_size,
                                                 thread_count)
from svelive.reconstruction.numerics import completed_window, window_estimate
from svelive.reconstruction.single import confidence_from_variance, estimate_variance, method_spec, run_method


def default_method(temporal: bool) -> str:
    """The method a Reconstructor uses when none is named: the library's single-frame default, with
    temporal fusion too (the motion tests compare a window mean computed beside any method,
    svelive.reconstruction.numerics.window_estimate, so they do not depend on its sharpness)."""
    return DEFAULT_METHOD

EXPOSURE_TIMINGS = ("mask", "integration")
#: A colour stream of the band refresh makes its chroma on every cell (and with it the white balance, a median over
#: the whole frame's cells) at least once in this many partial frames: elsewhere a still view's chroma is made on the
#: selected bands' cell rows only, with the last whole frame's white balance, and a change of the light's colour at
#: constant brightness (which selects no band) is followed within this many frames (about 2 s at 30 fps).
WHOLE_CHROMA_FRAMES = 64


@dataclass(frozen=True)
class SequenceResult:
    """One reconstructed frame of a stream.

    Attributes:
        image: float32 (H, W), radiance in DN at relative exposure 1, finite and >= 0; for a
            colour camera (H, W, 3) linear camera RGB (before white balance), whose luminance
            (``luminance``) the other fields describe.
        motion: bool (H, W), pixels flagged as moving (history reset or within-frame inconsistency).
        variance_of: computes ``variance`` (svelive.reconstruction.fusion.OutputVariance).
        lower_bound: bool (H, W), ``image`` is only the lower bound saturated samples imply.
        weight: float32 (H, W), 1 / n, n = frames fused into each pixel (1 without temporal fusion).
        moving_fraction: fraction of pixels in ``motion``.
        illumination_ratio: global brightness ratio (frame / history) divided out before the temporal test.
        method: the single-frame method used.
        frame_index: 0 for the first frame the Reconstructor processed (after a reset too).
        timings_ms: {"method": ..., "motion": ...}, wall time of the two stages.
        luminance: float32 (H, W) for a colour camera, Y = sum_c n_c RGB_c
            (svelive.reconstruction.colour); None for a monochrome one.
        reset: bool (H, W), the pixels that took this frame's values without their history (``motion``,
            and where the test flagged a pixel alone, a reading crossed the censor level or a side is a
            lower bound); None without a history to compare with (no fusion, a stream's first frame,
            after a reset or a method change).
        method_rows: the share of the frame's rows the single-frame method ran on: below 1 where the band
            refresh (``refresh``) kept settled bands, else 1 (its pixels on demand not counted).

    ``variance`` (float32 (H, W), predicted noise variance of ``image``, DN^2 at exposure 1;
    of the fused smooth estimate where detail sharpening moved a pixel), ``confidence``,
    ``frames_fused`` and ``still`` are computed on first access.
    """

    image: np.ndarray
    motion: np.ndarray
    variance_of: Callable[[], np.ndarray] = field(repr=False)
    lower_bound: np.ndarray
    weight: np.ndarray
    moving_fraction: float
    illumination_ratio: float
    method: str
    frame_index: int
    timings_ms: dict[str, float] = field(default_factory=dict)
    luminance: np.ndarray | None = None
    reset: np.ndarray | None = None
    method_rows: float = 1.0

    @property
    def plane(self) -> np.ndarray:
        """The (H, W) image the other fields describe: ``luminance`` for colour, else ``image``."""
        return self.image if self.luminance is None else self.luminance

    @cached_property
    def variance(self) -> np.ndarray:
        """float32 (H, W), DN^2: the predicted noise variance of ``plane``."""
        return self.variance_of()

    @cached_property
    def confidence(self) -> np.ndarray:
        """float32 (H, W) in [0, 1]: SNR / (1 + SNR) = L / (L + sigma), 0 where ``plane`` is a lower bound."""
        return confidence_from_variance(self.plane, self.variance, self.lower_bound)

    @cached_property
    def frames_fused(self) -> np.ndarray:
        """float32 (H, W), frames fused into each pixel (1 / weight)."""
        return np.reciprocal(self.weight)

    @cached_property
    def still(self) -> np.ndarray | None:
        """bool (H, W), the pixels the motion tests found still against the previous frame (``~reset``):
        they kept their history, and their frame differences are noise alone (what a noise tracker may
        read; ``~motion`` also holds pixels reset where readings crossed the censor level, which next to
        a moving bright object are most of its edges). None where ``reset`` is."""
        return None if self.reset is None else ~self.reset


@lru_cache(maxsize=8)
def own_reading_rows(pattern: Pattern, shape: tuple[int, int], sensor: Sensor,
                     scale: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(inverse, slope, floor), float32 (P, W) by row phase, read-only (svelive.reconstruction.fusion.FrameEstimate).

    Pixel (r, c) has exposure 1 / ``inverse[r % P, c]`` and its own estimate s / e has variance
    ``slope * L + floor`` at radiance L, times ``scale``. P is the tile's rows, or H for a per-pixel map.
    """
    _, inverse = exposure_maps(pattern, shape)
    period = shape[0] if pattern.pixel_map is not None else min(pattern.shape[0], shape[0])
    inverse = np.ascontiguousarray(inverse[:period])
    slope = inverse * np.float32(scale / sensor.effective_gain)
    floor = inverse * inverse * np.float32(scale * sensor.floor_variance)
    for array in (inverse, slope, floor):
        array.setflags(write=False)
    return inverse, slope, floor


class Reconstructor:
    """Motion-robust reconstruction of one stream of raw SVE frames.

    Args:
        pattern: the camera (svelive.Camera: pattern, colour filter, sensor, response), or
            the exposure pattern or its text form (the sensor then comes from the levels
            below and the raw dtype, the colour filter from ``cfa``).
        cfa: the colour filter layout when ``pattern`` is not a Camera.
        method: single-frame method name; changeable between frames through the
            ``method`` attribute (the history restarts then). None: the library's
            default (svelive.reconstruction.methods.DEFAULT_METHOD), with or without fusion.
        temporal: fuse consecutive frames where the scene is static.
        exposure_timing: ``"mask"`` when all exposures integrate over the same
            time (neutral-density mask, gain), ``"integration"`` when exposures
            are different integration times ending together.
        consistency: run the within-frame exposure-consistency test; None means
            on for ``integration`` timing, off for ``mask``.
        black_level, white_level, gain, read_noise: the sensor, as for svelive.reconstruct,
            when ``pattern`` is not a Camera: the stream makes its Camera from them once, the bit
            depth from the first frame's dtype (:attr:`camera`), and refuses frames of another
            type. A gain or read noise the camera does not give is
            estimated from the stream's own frames (:class:`svelive.noise.StreamNoise`): the first
            frame's single-frame estimate (as svelive.reconstruct's), then a
            :class:`svelive.noise.NoiseTracker` fed runs of consecutive frames with the pixels the
            motion tests found static, refitted on ``noise_schedule``; :attr:`noise` is the model in
            use. Until that model is trusted (a tracker's fit stating the variance to within
            ``noise_schedule.trusted_below``) each output is its frame's own estimate: fusion with a
            wrong model can be worse than none. The history is fused all along and kept when the
            model changes (its frames are weighed equally whatever the model). A given value is
            never overridden.
        noise_schedule: when the model is refined and trusted (svelive.noise.NoiseSchedule).
        noise_thread: refine the model on a thread of the stream's own (a fit takes about 250 ms CPU at
            1920x1200, which a live stream cannot stall for): a fit's model is taken when it is done,
            the frames meanwhile use the one before.
        motion_config: thresholds (svelive.reconstruction.config.MotionConfig).
        detail: with temporal fusion, sharpen static pixels that have history
            towards their own fused readings (svelive.reconstruction.fusion.sharpen).
        workers: threads for one frame: the strips of the method (where it takes
            a ``workers`` option) and of the motion stage are spread over them.
            The results do not depend on it; 1 keeps everything on the caller's thread.
        refresh: 0 (off, the default) or K in 1..64 (svelive.reconstruction.settle, issue 25): a monochrome
            stream with temporal fusion and method ``adaptive`` (no within-frame test, a nominal tile of sides
            dividing 16), once its noise model is trusted, runs the method per frame only on the bands of 64
            rows whose history is not settled (recent motion, a start or restart) and a round-robin 1 / K of
            the others; skipped pixels keep their history's mean, pixels the test resets there get their
            estimate on demand. Which bands run is decided by the history a frame is fused into, so frames
            estimated ahead fuse as the sequential stream's, bit for bit. Other streams ignore it (colour ones
            unless ``colour_refresh``). The live service's default (svelive.reconstruction.live.LIVE_REFRESH).
        colour_refresh: ``refresh`` for a colour stream too (issue 25; off by default in the library, on in the
            live service), on the bands of its folded luminance; once its history holds a chroma, a frame's
            chroma is made (and fused) only on the cell rows of the selected bands and the method's reach around
            them, the history's cells kept elsewhere, with the last whole frame's white balance (the whole chroma at
            least every WHOLE_CHROMA_FRAMES partial frames; the fold and the refinement still run on every pixel);
            a colour frame estimated ahead of another history is estimated (again) when fused. Its output differs
            from refresh 0's as a monochrome stream's does (docs/benchmarks.md, "A colour band refresh").
        **method_options: passed to the method.

    ``process`` is meant for one worker thread, or split: ``estimate`` (no history; several
    frames at once on several threads) then ``fuse`` (in frame order, one thread at a time),
    which uses each core for a whole frame instead of spreading one frame's strips over them
    (``workers``), whose threads wait on each other; ``method``, ``reset()`` and ``state()``
    may be called from any thread.
    """

    def __init__(self, pattern: Pattern | str | Camera, *, cfa: ColourFilter | str | None = None,
                 method: str | None = None, temporal: bool = True,
                 exposure_timing: str = "mask", consistency: bool | None = None, black_level: float = 0,
                 white_level: float | None = None, gain: float | None = None, read_noise: float | None = None,
                 motion_config: MotionConfig | None = None, detail: bool = True, workers: int = 1,
                 noise_schedule: NoiseSchedule | None = None, noise_thread: bool = False, refresh: int = 0,
                 colour_refresh: bool = False, **method_options) -> None:
        if isinstance(workers, bool) or not isinstance(workers, int) or not 1 <= workers <= 64:
            raise SveliveError(f"workers must be an integer 1..64, got {workers!r}")
        if exposure_timing not in EXPOSURE_TIMINGS:
            raise SveliveError(f"exposure timing must be one of {', '.join(EXPOSURE_TIMINGS)}, got {exposure_timing!r}")
        if isinstance(pattern, Camera):
            if cfa is not None or any(v not in (None, 0) for v in (black_level, white_level, gain, read_noise)):
                raise SveliveError("give the colour filter and sensor levels inside the Camera, not beside it")
            self.camera: Camera | None = pattern
            pattern = pattern.require_pattern()
        else:
            self.camera = None  # built once from the levels below and the first frame's dtype (_camera_for)
        self._loose_dtype: np.dtype | None = None  # that dtype, for a stream given loose levels
        self.pattern = Pattern.parse(pattern)
        self.cfa = self.camera.cfa if self.camera is not None else (None if cfa is None else ColourFilter.parse(cfa))
        self.temporal = bool(temporal)
        self.exposure_timing = exposure_timing
        self.consistency = exposure_timing == "integration" if consistency is None else bool(consistency)
        if self.consistency and self.pattern.pixel_map is not None:
            raise SveliveError("the exposure-consistency test needs a nominal tile, not a per-pixel exposure map")
        self.sensor_levels = dict(black_level=black_level, white_level=white_level, gain=gain, read_noise=read_noise)
        self.motion_config = motion_config or MotionConfig()
        self.detail = bool(detail)
        self.workers = workers
        # one pool for the stream's whole life: a pool per frame costs thread start-ups and grows memory
        self._pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="svelive-strip") if workers > 1 else None
        self.method_options = dict(method_options)
        if isinstance(refresh, bool) or not isinstance(refresh, (int, np.integer)) or not 0 <= refresh <= 64:
            raise SveliveError(f"refresh must be an integer 0..64 (0: off), got {refresh!r}")
        self.refresh = int(refresh)
        self.colour_refresh = bool(colour_refresh)
        # partial frames estimated and not fused yet (weakly: one never fused leaves with its Estimated), whose
        # count ahead of the frames fused gives an estimate's hint its round-robin turn
        self._in_flight: weakref.WeakSet = weakref.WeakSet()
        self._fused_partials = 0  # partial frames fused: the round-robin's turn
        self._hint_changes = [0, 0]  # bands fuse computed beyond the estimates' hints, and dropped from them
        self._reestimates = 0  # colour frames fuse estimated again (_reestimated)
        self._last_variance: np.ndarray | None = None  # the last fused partial frame's variance (placeholders)
        self._window_tables: dict = {}  # settle.window_rows' tables, kept across frames
        self._unsettled: tuple | None = None  # (weakref.ref of a history, its unsettled pixels by band): _selection
        self._moving: tuple | None = None  # (shape, the band motion, its bands' pixels, its moving bands): _selection
        self.last_partial: dict | None = None  # the last fused partial frame's counts (benchmarks)
        self._band_motion: list[np.ndarray] = []  # moving pixels per band (every 4th row) of the last frames
        self._last_ratio = 1.0  # the last fused frame's brightness ratio
        self._lock = threading.Lock()
        self._method = self._checked(method)
        self._history: TemporalState | None = None
        self._chroma: np.ndarray | None = None  # a colour stream's fused chroma cells (5, Hc, Wc), fuse_chroma
        self._white: np.ndarray | None = None  # the white balance of the last fused colour frame (its chroma's)
        # a colour stream's evidence of its luminance's noise and its floor (luminance_noise)
        self._spread: LuminanceNoise | None = None
        self._share_cells: ShareError | None = None  # the spread of _chroma's shares where kept (share_error_cells)
        self._generation = 0  # bumped by reset() and method changes: a frame in flight then drops its history
        self._frames = 0
        self._last_moving = 0.0
        self.noise_schedule = noise_schedule or NoiseSchedule()
        self._noise_executor = (ThreadPoolExecutor(max_workers=1, thread_name_prefix="svelive-noise")
                                if noise_thread else None)
        self._noise_lock = threading.Lock()  # the stream's noise model: first frame (any thread), fuse (in order)
        self._noise: StreamNoise | None = None
        self._noise_base: Camera | None = None  # the camera (without the estimate) the model is of
        self._noise_camera: tuple[NoiseEstimate, Camera, Camera] | None = None  # (model, base, base with it)

    def _checked(self, method: str | None) -> str:
        if method is None:
            method = default_method(self.temporal)
        name = method
        if name not in METHODS:
            raise SveliveError(f"unknown method {name!r}; choose from {', '.join(METHODS)}")
        return name

    @property
    def _threads(self) -> int | Executor:
        """What spreads a frame's pieces over this stream's threads (base.map_on)."""
        return self._pool if self._pool is not None else self.workers

    @property
    def _floor_weight(self) -> np.float32:
        """1 / max_history: a history's weight above it is unsettled (fewer than max_history frames)."""
        return np.float32(1.0 / self.motion_config.max_history)

    @property
    def method(self) -> str:
        """The single-frame method; setting it restarts the history with the next frame."""
        return self._method

    @method.setter
    def method(self, name: str | None) -> None:
        name = self._checked(name)
        with self._lock:
            if name != self._method:
                self._method = name
                self._history = self._chroma = self._spread = self._white = self._share_cells = None
                self._generation += 1

    def close(self) -> None:
        """Stop the stream's pool of worker threads (with ``workers`` > 1; later frames make a pool per frame) and
        its noise thread (a fit under way is finished; later frames refine the model in line, as a stream
        without ``noise_thread`` does)."""
        pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=False)
        with self._noise_lock:
            noise_pool, self._noise_executor = self._noise_executor, None
            if self._noise is not None:
                self._noise.executor = None
        if noise_pool is not None:
            noise_pool.shutdown(wait=False, cancel_futures=True)

    def continue_noise(self, other: Reconstructor) -> None:
        """Take over ``other``'s noise model, its tracker and its noise thread (``other`` then refines it no
        more): a stream of the same camera that replaces ``other`` (the live service's step changes) goes on
        from the model ``other`` has, instead of estimating one afresh. Call before this stream's first frame."""
        with other._noise_lock:
            noise, base, executor = other._noise, other._noise_base, other._noise_executor
            other._noise = other._noise_base = other._noise_camera = None
            other._noise_executor = None if noise is not None else executor
        if noise is None:
            return
        with self._noise_lock:
            own, self._noise_executor = self._noise_executor, executor
            self._noise, self._noise_base, self._noise_camera = noise, base, None
        if own is not None and own is not executor:
            own.shutdown(wait=False)

    def noise_state(self) -> dict[str, object] | None:
        """JSON-ready: the model the stream estimates (:attr:`noise`, its ``to_dict``) with ``trusted``, the
        tracker's ``fits`` and the last ``error`` of its noise thread; None when the camera gives its model
        (or before the first frame)."""
        if self.camera is not None and not _needs_noise(self.camera):
            return None
        with self._noise_lock:
            noise = self._noise
        if noise is None or noise.estimate is None:
            return None
        return {**noise.estimate.to_dict(), "trusted": noise.trusted, "fits": noise.fits, "error": noise.error}

    def refresh_state(self) -> dict[str, object] | None:
        """JSON-ready, None with ``refresh`` off: ``refresh`` (K), ``applies`` (this stream skips bands once its
        model is trusted: ``adaptive``, fusion, a supported tile, monochrome or with ``colour_refresh``), and of the last fused frame that
        took the partial path ``bands`` and ``computed`` (bands the method ran on) and ``on_demand_px``, or None
        before one; ``hint_added`` and ``hint_dropped``: bands :meth:`fuse` computed beyond its frames' estimates
        and dropped from them, over the stream's life (frames estimated ahead of the history they are fused into);
        ``reestimated``: colour frames estimated ahead that :meth:`fuse` estimated again (their chroma kept the cells
        of another history than the one they are fused into).
        """
        if not self.refresh:
            return None
        with self._lock:
            method = self._method
        camera = self.camera
        applies = camera is not None and self._settles(method, camera)
        last = self.last_partial
        return {"refresh": self.refresh, "applies": applies,
                "bands": None if last is None else last.get("bands"),
                "computed": None if last is None else last.get("computed"),
                "on_demand_px": None if last is None else last.get("demand_px", 0),
                "hint_added": self._hint_changes[0], "hint_dropped": self._hint_changes[1],
                "reestimated": self._reestimates}

    def __enter__(self) -> Reconstructor:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def reset(self) -> None:
        """Forget the history: the next frame is processed as the first of a stream."""
        with self._lock:
            self._history = self._chroma = self._spread = self._white = self._share_cells = None
            self._generation += 1
            self._frames = 0
            self._band_motion = []

    @property
    def noise(self) -> NoiseEstimate | None:
        """The noise model in use: the camera's own (source "given") when it gives gain and read noise, else
        the estimate from this stream's frames (source "estimated", or "default" where the frames could not
        tell it; with its standard uncertainties), None before the first frame."""
        sensor = self.camera.sensor if self.camera is not None else None
        if sensor is None and self.sensor_levels["gain"] is not None and self.sensor_levels["read_noise"] is not None:
            return NoiseEstimate(float(self.sensor_levels["gain"]), float(self.sensor_levels["read_noise"]),
                                 0.0, 0.0, 0, "given")
        if sensor is not None and not _needs_noise(self.camera):
            return NoiseEstimate.given(sensor)
        with self._noise_lock:
            return None if self._noise is None else self._noise.estimate

    @property
    def noise_trusted(self) -> bool:
        """Whether the noise model in use is trusted, so that fusion shapes the output (given, or a fit of
        the stream's frames within ``noise_schedule.trusted_below``)."""
        if self.camera is not None and not _needs_noise(self.camera):
            return True
        with self._noise_lock:
            return self._noise is not None and self._noise.trusted

    def _with_noise(self, raw: np.ndarray, camera: Camera,
                    signal: np.ndarray | None) -> tuple[Camera, bool, NoiseEstimate]:
        """``camera`` with the stream's noise model where its sensor lacks gain or read noise (the first
        frame's own estimate before any fit), whether that model is trusted, and the model. ``raw``: uint
        (H, W)."""
        if not _needs_noise(camera):
            return camera, True, NoiseEstimate.given(camera.sensor)
        with self._noise_lock:
            if self._noise is None or self._noise_base != camera:
                self._noise, self._noise_base, self._noise_camera = (
                    StreamNoise(self.noise_schedule, executor=self._noise_executor), camera, None)
            noise = self._noise
            model = noise.estimate if noise.estimate is not None else noise.first(raw, camera, signal=signal)
            cached = self._noise_camera
            if cached is None or cached[0] is not model or cached[1] != camera:
                cached = self._noise_camera = model, camera, camera.replace(sensor=model.apply(camera.sensor))
            return cached[2], noise.trusted, model

    def _observe_noise(self, estimated: Estimated, reset: np.ndarray | None) -> None:
        """Feed a fused frame to the stream's noise model (on its schedule); ``reset``: the pixels that did
        not keep their history (:attr:`SequenceResult.reset`), None where the frame has none to compare with.

        Not ``~motion``: a pixel is also reset, without counting as motion, where a reading crossed the
        censor level; next to a bright object crossing a dark background those are most of the edge that
        moved (a 2x-peak disc at 5 stops under: 1.6 % of the frame flagged, 5 % changed; the tracker read
        the gain 3.9x with the unflagged edges, within 2 % without them)."""
        if estimated.raw is None or estimated.base is None or not _needs_noise(estimated.base):
            return
        with self._noise_lock:
            if self._noise is None or self._noise_base != estimated.base:
                return
            still = None if reset is None or not self._noise.needs_static() else ~reset
            self._noise.observe(estimated.raw, estimated.base, still, signal=estimated.signal)

    def state(self) -> dict[str, object]:
        """JSON-ready state: method, temporal, exposure_timing, consistency, frames, moving_fraction."""
        with self._lock:
            return {"method": self._method, "temporal": self.temporal, "exposure_timing": self.exposure_timing,
                    "consistency": self.consistency, "frames": self._frames,
                    "moving_fraction": self._last_moving}

    def _camera_for(self, raw: np.ndarray | Frame) -> Camera:
        """The camera of this stream; a Frame's own camera must agree with it on colour. A stream given loose
        levels instead of a Camera gets one here, once: ``Camera`` of its pattern, colour filter and levels,
        the bit depth from the first frame's dtype (unless the white level says more); later frames are checked
        against it as any stream's are."""
        camera = self.camera
        if camera is None or self._loose_dtype is not None:
            dtype = np.asarray(getattr(raw, "raw", raw)).dtype
            with self._lock:
                if self.camera is None:
                    self.camera = camera_for_raw(np.empty(0, dtype), self.pattern, cfa=self.cfa,
                                                 **self.sensor_levels)
                    self._loose_dtype = dtype
                camera = self.camera
            if dtype != self._loose_dtype:
                raise SveliveError(f"this stream's camera was made from its first frame, {self._loose_dtype} "
                                   f"({camera.sensor.bits}-bit), but a frame is {dtype}: give every frame the "
                                   "same type, or a Camera")
        if isinstance(raw, Frame) and raw.camera.cfa != camera.cfa:
            def kind(c: Camera) -> str:
                return "monochrome" if c.cfa is None else f"colour ({c.cfa.name})"
            raise SveliveError(f"frame {raw.frame_id} is {kind(raw.camera)} but this stream reconstructs "
                               f"{kind(camera)} frames: give the matching colour filter (--cfa)")
        return camera

    def _estimate(self, raw: np.ndarray | Frame, method: str,
                  camera: Camera) -> tuple[SveInput, Estimate, colour.Joint | None]:
        """(input, estimate with its variance, the joint parts of a colour frame or None), ``camera``
        the stream's with its noise model.

        A colour frame's estimate is of its luminance (the stream colours the fused luminance),
        its variance that of the luminance's monochrome SVE frame (``parts.luminance_input``)."""
        inp = prepare(getattr(raw, "raw", raw), camera)
        spec = method_spec(method)
        options = dict(self.method_options)
        if spec.variance:
            options["return_variance"] = True
        if spec.workers and "workers" not in options:
            options["workers"] = self._pool if self._pool is not None else self.workers
        if spec.window and (self.temporal or self.consistency):
            options["window"] = True  # the motion tests' window mean from the method's own pass
        if inp.cfa is None:
            estimate = run_method(inp, method, **options)
            return inp, replace(estimate, variance=estimate_variance(estimate, inp)), None
        spec.check_options(options)
        # a single frame without the within-frame test (which changes the luminance) is coloured in the
        # refinement's pass; fuse takes its RGB (parts.estimate.image) and adds the lattice's channels
        rgb = not self.temporal and not self.consistency and spec.variance
        parts = colour.joint(inp, spec, rgb=rgb, refined=not self.temporal, lattice=False, lights=False, **options)
        estimate = parts.estimate
        if rgb:
            estimate = replace(estimate, image=estimate.luminance, luminance=None)
        return inp, replace(estimate, variance=estimate_variance(estimate, parts.luminance_input)), parts

    def process(self, raw: np.ndarray | Frame) -> SequenceResult:
        """Reconstruct the next frame of the stream: a Frame, or a raw uint8/uint16 (H, W) array
        (black level included) of this stream's camera. ``fuse(estimate(raw))``."""
        return self.fuse(self.estimate(raw))

    def estimate(self, raw: np.ndarray | Frame) -> Estimated:
        """The part of :meth:`process` that does not depend on the stream's history: the method's
        estimate and what the motion tests compare. Safe to call from several threads at once, on
        different frames (a live service estimates two frames on two cores while it fuses in
        order); pass each result to :meth:`fuse` in frame order."""
        with self._lock:
            method, generation = self._method, self._generation
        t0 = time.perf_counter()
        base = self._camera_for(raw)
        array = np.asarray(getattr(raw, "raw", raw))
        signal = None
        if _needs_noise(base) and base.response is not None:
            signal = prepare(array, base).signal  # the tracker reads the linearised signal
        camera, trusted, model = self._with_noise(array, base, signal)
        partial = chroma_of = None
        if trusted and self._settles(method, camera):  # (an untrusted model's output is the frame's own estimate)
            inp, est, partial, parts, chroma_of = self._estimate_partial(raw, camera)
            if est is None:  # a colour frame behind frames in flight: all of it when fused (_estimate_partial)
                return Estimated(None, None, None, None, method, generation, (time.perf_counter() - t0) * 1e3, 0.0,
                                 array, base, trusted, signal, camera, model, inp, partial, chroma_of)
        else:
            inp, est, parts = self._estimate(raw, method, camera)
        return self._estimated(inp, est, parts, partial, chroma_of, method, generation, t0, array, base, trusted,
                               signal, camera, model)

    def _estimated(self, inp: SveInput, est: Estimate, parts: colour.Joint | None, partial, chroma_of,
                   method: str, generation: int, t0: float, array: np.ndarray, base: Camera, trusted: bool,
                   signal: np.ndarray | None, camera: Camera, model: NoiseEstimate) -> Estimated:
        """:meth:`estimate`'s result from the method's estimate (started at ``t0``): the motion tests' inputs."""
        t1 = time.perf_counter()
        lum = inp if parts is None else parts.luminance_input  # the monochrome frame of ``image``
        inconsistency = window = None
        if partial is not None:
            window = est.window
        elif self.temporal or self.consistency:
            # what the motion tests compare: a window mean beside the method's estimate, whatever the method
            # (made in the method's own pass where it can: bit-identical)
            window = (completed_window(est.window, est.image, est.variance) if est.window is not None
                      else window_estimate(lum, est.image, est.variance, self._threads))
        if self.consistency:
            # the test reads each level's readings with its nominal exposure: a colour frame's
            # readings divided by their channel's share instead of the share folded into e
            tested = lum if not lum.folded else colour.luminance_input(inp, parts.interpolation, exposures=False)
            inconsistency = exposure_consistency(*window, tested, self.motion_config, workers=self.workers,
                                                 executor=self._pool)
        frame = None
        if self.temporal:
            if parts is None:
                frame = FrameEstimate(est.image, est.variance, est.lower_bound, lum.censored, lum.signal,
                                      *own_reading_rows(self.pattern, inp.shape, inp.sensor), *window)
            else:
                frame = FrameEstimate(est.image, est.variance, est.lower_bound, lum.censored, lum.signal, None,
                                      *own_reading_scales(inp.sensor), *window, exposure=lum.exposure)
        return Estimated(est, parts, frame, inconsistency, method, generation, (t1 - t0) * 1e3,
                         (time.perf_counter() - t1) * 1e3, array, base, trusted, signal, camera, model,
                         None if parts is None else inp, partial, chroma_of)

    @staticmethod
    def _chroma_source(history: TemporalState | None, chroma_history: np.ndarray | None, white: np.ndarray | None,
                       selected: np.ndarray, shape: tuple[int, int], cell: tuple[int, int],
                       tick: int) -> np.ndarray | None:
        """The fused chroma (5, Hc, Wc) a colour frame with the band refresh keeps on the cell rows its selection
        (``selected``, bool per band) skips, or None where it makes its chroma on every cell (every band
        selected, no chroma history of its size or no white balance kept, or the round-robin's turn ``tick`` a
        multiple of :data:`WHOLE_CHROMA_FRAMES`): :meth:`_estimate_partial`."""
        hc, wc = (-(-n // c) for n, c in zip(shape, cell))
        if (selected.all() or history is None or chroma_history is None or white is None
                or chroma_history.shape != (5, hc, wc) or tick % WHOLE_CHROMA_FRAMES == 0):
            return None
        return chroma_history

    def _reestimated(self, estimated: Estimated, history: TemporalState | None,
                     chroma_history: np.ndarray | None, white: np.ndarray | None) -> Estimated:
        """A colour frame estimated ahead (its chroma kept another history's cells, or its selection differs from
        the one of the history it is fused into, ``history``): estimated again as the sequential stream would
        have, from ``history``, its chroma ``chroma_history`` and ``white`` and the round-robin's turn now."""
        self._in_flight.discard(estimated.partial)
        self._reestimates += 1
        t0 = time.perf_counter()
        ahead = history, self._fused_partials, chroma_history, white
        inp, est, partial, parts, chroma_of = self._estimate_partial(estimated.raw, estimated.camera, ahead,
                                                                     estimated.colour_input)
        return self._estimated(inp, est, parts, partial, chroma_of, estimated.method, estimated.generation, t0,
                               estimated.raw, estimated.base, estimated.trusted, estimated.signal, estimated.camera,
                               estimated.noise)

    def _on_demand(self, partial, fused, frame: FrameEstimate, predicted: list[tuple[int, int]],
                   history: TemporalState) -> Fused:
        """The pixels the test reset in rows the method skipped (``predicted``; svelive.reconstruction.settle):
        where they moved (``motion``), the history is a lower bound or the window means differ beyond
        settle.UNSTABLE_SIGMAS, this frame's
        estimate on demand, into the frame's arrays, the history's mean and own readings and the output; the
        others (reset only because a reading in their window crossed the censor level, the window means
        agreeing within that) keep their history as it was (times the brightness ratio): they skip this frame, as the
        method did, rather than average two estimates of different kinds."""

        ratio = fused.illumination_ratio
        scale = np.float32(ratio) if abs(ratio - 1.0) > RATIO_TOLERANCE else np.float32(1)
        state = fused.state
        tested, tested_variance = frame.tested
        # (the pass judged each pixel: fusion._skipped_row; here the taking spreads through crossed readings)
        wy, wx = (support_size(n) // 2 for n in self.pattern.shape)  # the fusion's censoring window
        no_rows = np.empty((0, 0), np.float32)
        ys, xs, kept, given = settle.skipped_resets(
            fused.skipped, ~partial.rows, fused.reset, frame.censored, history.censored, history.tested, tested,
            scale, wy, wx, state.weight, no_rows if state.test is None else state.test, state.censored)
        # (the pass's halo first unless most of the last frame's were the wide fallback's, which reads farther)
        last = self.last_partial
        narrow = last is None or 2 * last.get("demand_wide", 0) <= last.get("demand_px", 0)
        ys, xs, (img, low, var), stats = settle.on_demand(partial, ys, xs, self._threads, narrow)
        partial.stats.update(stats, kept_px=kept)
        if fused.row_counts is not None and given.size:  # (the pass's unsettled counts of the rows given weight 1)
            rows = np.unique(given // frame.image.shape[1])
            rows = rows[rows % COUNTED_STEP == 0]
            fused.row_counts[rows, 1] = np.count_nonzero(state.weight[rows] > self._floor_weight, axis=1)
        if fused.noise is not None and given.size:  # the pass's luminance noise evidence where weight 1 came back
            np.put(fused.noise.spread, given, np.float32(0))
            noise_floor(fused.noise.spread, state.weight, fused.noise.cell, fused.noise.floor,
                        rows=np.unique(given // (frame.image.shape[1] * fused.noise.cell[0])))
        if not ys.size:
            return fused
        at = ys * frame.image.shape[1] + xs  # (flat indices: np.put and np.take, x0.5 of (ys, xs) indexing's time)
        for target, value in ((frame.image, img), (frame.variance, var), (frame.bound, low), (state.mean, img),
                              (fused.image, img)):
            np.put(target, at, value)
        inverse = (np.float32(1) / np.take(frame.exposure, at) if frame.exposure is not None
                   else frame.inverse[ys % frame.inverse.shape[0], xs])
        np.put(state.own, at, np.where(np.take(frame.censored, at), img, np.take(frame.signal, at) * inverse))
        lost = np.isinf(np.take(tested_variance, at))  # the window mean is the method's estimate there
        if lost.any():
            there = at[lost]
            for target, value in ((tested, img), (tested_variance, var), (state.tested, img)):
                np.put(target, there, value[lost])
        return fused

    def _settles(self, method: str, camera: Camera) -> bool:
        """Whether this frame takes the partial path (``refresh``; svelive.reconstruction.settle)."""
        if not (self.refresh > 0 and self.temporal and not self.consistency and method == "adaptive"):
            return False
        if camera.cfa is None:
            return settle.supports(camera.pattern)
        cell = joint_period(camera.pattern.shape, camera.cfa.shape)
        return self.colour_refresh and settle.supports_colour(camera.pattern, camera.cfa.shape, cell)

    def _selection(self, history: TemporalState | None, tick: int, shape: tuple[int, int],
                   band_motion: list[np.ndarray], last_ratio: float,
                   last_variance: np.ndarray | None) -> np.ndarray:
        """bool (bands,): the bands of a frame of ``shape`` the method runs on, given the history it is fused
        into (svelive.reconstruction.settle): every band without a history of this shape (or before a partial
        frame was fused: ``last_variance``, its variance), or after a frame whose brightness ratio
        (``last_ratio``) moved; else those where something moved within the last max_history frames
        beyond the false alarms the stream shows (``band_motion``: moving pixels per band on every 4th row, of
        the last fused frames; settle.moving_bands), those whose
        history is mostly unsettled (a stream's start, a restart) and the round-robin's ``tick``-th 1 / K."""

        h, w = shape
        spans = settle.bands(h)
        if (history is None or history.mean.shape != shape or last_variance is None
                or last_variance.shape != shape or abs(last_ratio - 1.0) > RATIO_TOLERANCE):
            return np.ones(len(spans), bool)
        # not the false alarms this stream's test shows, nor the pixels reset where a reading crossed the censor level
        # (a frame's hint and its fuse read the same band motion and history: each judged once)
        moving = self._moving
        if (moving is None or moving[0] != shape or len(moving[1]) != len(band_motion)
                or any(a is not b for a, b in zip(moving[1], band_motion))):
            # (the counts' pixels: every COUNTED_STEP-th row)
            sampled = np.array([-(-(b.stop - b.start) // COUNTED_STEP) for b in spans]) * w
            moving = self._moving = (shape, band_motion, sampled,
                                     settle.moving_bands(band_motion, sampled, 2 * int(self.motion_config.widen) + 1))
        _, _, sampled, selected = moving
        selected = selected.copy()
        cached = self._unsettled
        if cached is not None and cached[0]() is history:
            unsettled = cached[1]
        else:
            unsettled = settle.band_counts(history.weight[::COUNTED_STEP] > self._floor_weight)
            self._unsettled = weakref.ref(history), unsettled
        selected |= unsettled > settle.UNSETTLED_SHARE * sampled
        # the round-robin in K runs of bands (a run's halo rows are computed for nothing)
        selected |= np.arange(len(spans)) * self.refresh // len(spans) == tick % self.refresh
        return selected

    def _selection_state(self) -> tuple[list[np.ndarray], float, np.ndarray | None]:
        """(band motion, last brightness ratio, last partial frame's variance) as the last fused frame left
        them: what :meth:`_selection` reads besides the history. Called under ``_lock`` (:meth:`estimate`), or by
        :meth:`fuse`, their only writer."""
        return list(self._band_motion), self._last_ratio, self._last_variance

    def _estimate_partial(self, raw: np.ndarray | Frame, camera: Camera, ahead: tuple | None = None,
                          prepared: SveInput | None = None):
        """(input, estimate with the window mean, settle.Partial, a colour frame's joint parts or None, its
        Estimated.chroma_of or None): the method on the bands the latest history asks for, the window mean
        everywhere. The selection is a hint: the frame may be fused into a later history (frames estimated ahead),
        and :meth:`fuse` then makes it the selection of that history. A colour frame (``colour_refresh``): the
        selection first, then its chroma (on the cell rows of the selected bands and of the method's halo around
        them where the history holds a chroma of its size: the history's fused cells elsewhere, colour.partial_chroma,
        with the last whole frame's white balance; else, and every WHOLE_CHROMA_FRAMES partial frames, on every
        cell) and the folded luminance (colour.joint's, every pixel), then the bands of that luminance, a monochrome
        input of per-pixel exposures (``partial.inp``). ``ahead``: (history, round-robin turn, its chroma, its white
        balance) to take instead of the stream's (:meth:`fuse`, a colour frame estimated ahead: :meth:`_reestimated`),
        ``prepared`` the frame's input prepared already.

        A colour frame estimated behind frames in flight (estimated, not fused yet) that would keep the history's
        chroma is estimated when it is fused (each of those frames leaves another chroma, so :meth:`fuse` would
        estimate it again): only its input is prepared, returned with no estimate (None), a marker of it in
        flight as its Partial and that marker as its kept chroma."""

        inp = prepare(getattr(raw, "raw", raw), camera, workers=self._threads) if prepared is None else prepared
        h, w = inp.shape
        # (a monochrome frame's noise model, from the frame alone, on the pool while this thread makes the selection;
        # a colour frame's reads its folded luminance, made after the selection)
        pending = self._pool.submit(noise_model, inp) if self._pool is not None and inp.cfa is None else None
        with self._lock:
            if ahead is None:
                hint, tick = self._history, self._fused_partials + len(self._in_flight)
                chroma_history, white = self._chroma, self._white
            else:
                hint, tick, chroma_history, white = ahead
            selected = self._selection(hint, tick, (h, w), *self._selection_state())
            behind = ahead is None and len(self._in_flight) > 0
        colour_input = chroma_of = None
        if inp.cfa is not None:  # colour.joint's steps before its method, as a stream takes them
            colour_input = inp
            cell = colour.cell_layout(inp.pattern, inp.cfa).cell
            source = self._chroma_source(hint, chroma_history, white, selected, (h, w), cell, tick)
            if behind and source is not None:
                marker = _Deferred()
                with self._lock:
                    self._in_flight.add(marker)
                return inp, None, marker, None, (marker, None, None)
            rows = ch = None
            if source is not None:
                rows = _chroma_rows(selected, h, cell[0], source.shape[1], settle.halo_for(inp.pattern)[0])
                ch = colour.partial_chroma(inp, settle.runs(rows), source, white)
            chroma_of = source, selected.copy(), rows
            ch, inter, inp = colour.fold_luminance(inp, False, True, self._threads, ch=ch)
        noise = noise_model(inp) if pending is None else pending.result()
        with self._lock:
            partial = settle.Partial(inp, noise, selected, settle.band_mask(selected, h),
                                     None if selected.all() else weakref.ref(hint), tick,
                                     dict(bands=len(selected), computed=int(np.count_nonzero(selected))))
            self._in_flight.add(partial)  # (at once: a frame estimated beside it takes the next turn)
        image, lower, variance = (np.empty((h, w), np.float32), np.empty((h, w), bool),
                                  np.empty((h, w), np.float32))
        window = np.empty((2, h, w), np.float32)  # (rows the pass does not make are made below)
        settle.method_on_bands(inp, noise, selected, image, lower, variance, window, self._threads)
        skipped = settle.band_rows(~selected, h)
        # the skipped rows' estimate and bound are the history's (fuse writes them, times its brightness ratio),
        # their variance the last fused frame's (fuse writes it too); the window mean where the method did not make
        # it, the history's mean where its window holds no uncensored reading (with an infinite variance: fuse's
        # tests pass over such a pixel, and it takes this frame's estimate on demand once the fusion resets it)
        if skipped:
            settle.window_rows(inp, hint.mean, _infinite((h, w)), skipped, window[0], window[1],
                               self._window_tables, self._threads)
        if not _shares_window(inp):
            settle.window_rows(inp, image, variance, settle.band_rows(selected, h), window[0], window[1],
                               self._window_tables, self._threads)
        for a, b in settle.band_rows(selected, h):  # (the window rows made here hold no infinite variance)
            completed_window((window[0, a:b], window[1, a:b]), image[a:b], variance[a:b])
        est = Estimate(image, lower, variance, window=(window[0], window[1]))
        if colour_input is None:
            return inp, est, partial, None, None
        return colour_input, est, partial, colour.Joint(est, inp, ch, inter), chroma_of

    def _settle_at_fuse(self, partial, frame: FrameEstimate, history: TemporalState | None) -> None:
        """Make a partial frame's bands those the stream selects for the history it is fused into (``history``),
        whatever its estimate's hint took (svelive.reconstruction.settle): the bands the hint skipped and the
        selection wants are computed now (their rows alone, and their window mean completed with them); the
        bands the hint computed and the selection skips take the history's window level where their window
        holds no uncensored reading, as a skipped band does; skipped rows whose hint was another history take
        this one's mean there; every skipped row takes the last fused partial frame's variance (a placeholder:
        the output's variance there, :class:`OutputVariance`). The frame then fuses as the sequential stream's
        would, bit for bit, however far ahead it was estimated. In ``frame``'s and ``partial``'s arrays."""
        h, w = frame.image.shape
        selected = self._selection(history, self._fused_partials, (h, w), *self._selection_state())
        hinted = partial.computed
        missing, extra = selected & ~hinted, hinted & ~selected
        level, noise = frame.test, frame.test_variance
        if missing.any():
            settle.method_on_band_rows(partial.inp, partial.noise, missing, frame.image, frame.bound, frame.variance,
                                       self._threads)
            # (the skipped rows' lost windows: infinite, so completed here)
            for a, b in settle.band_rows(missing, h):
                completed_window((level[a:b], noise[a:b]), frame.image[a:b], frame.variance[a:b])
        if extra.any():
            settle.window_rows(partial.inp, history.mean, _infinite((h, w)), settle.band_rows(extra, h), level,
                               noise, self._window_tables, self._threads)
        if partial.hint is None or partial.hint() is not history:  # (a hint gone is not this history)
            for a, b in settle.band_rows(~selected & ~hinted, h):
                lost = np.isinf(noise[a:b])
                if lost.any():
                    level[a:b][lost] = history.mean[a:b][lost]
        last = self._last_variance

        def placeholder(span: tuple[int, int]) -> None:
            frame.variance[span[0]:span[1]] = last[span[0]:span[1]]

        map_on(self._threads, placeholder, settle.pieces(settle.band_rows(~selected, h),
                                                         thread_count(self._threads)))
        partial.computed[:] = selected
        partial.rows[:] = settle.band_mask(selected, h)
        partial.hint = None if selected.all() else weakref.ref(history)
        partial.stats.update(computed=int(np.count_nonzero(selected)), added=int(np.count_nonzero(missing)),
                             dropped=int(np.count_nonzero(extra)))
        self._hint_changes = [self._hint_changes[0] + partial.stats["added"],
                              self._hint_changes[1] + partial.stats["dropped"]]

    def fuse(self, estimated: Estimated) -> SequenceResult:
        """The rest of :meth:`process`: the frame's :meth:`estimate` fused into the stream's history
        (with temporal fusion), the within-frame test applied, colour added. Call it with the
        stream's frames in order, from one thread at a time. A frame estimated before a
        ``reset()`` or a method change starts from no history and leaves none."""
        t1 = time.perf_counter()
        est, parts, inconsistency = estimated.estimate, estimated.parts, estimated.inconsistency
        with self._lock:
            current = estimated.generation == self._generation
            history, index = (self._history, self._frames) if current else (None, 0)
            chroma_history = self._chroma if current else None
            white = self._white if current else None
            spread = self._spread if current else None
            share_cells = self._share_cells if current else None
            if current:  # (taken: its cells are updated in place below and kept again with the fused chroma)
                self._share_cells = None
        if estimated.chroma_of is not None:  # (a colour frame of the band refresh)
            source, computed, _ = estimated.chroma_of
            inp = estimated.colour_input
            shape = inp.shape
            selected = self._selection(history, self._fused_partials, shape, *self._selection_state())
            if (source is not self._chroma_source(history, chroma_history, white, selected, shape,
                                                  colour.cell_layout(inp.pattern, inp.cfa).cell, self._fused_partials)
                    or (source is not None and not np.array_equal(computed, selected))):
                estimated = self._reestimated(estimated, history, chroma_history, white)
                est, parts = estimated.estimate, estimated.parts
        previous = history
        image, variance = est.image, est.variance
        held = self.temporal and not estimated.trusted
        reset, method_rows = None, 1.0
        if self.temporal:
            frame = estimated.frame
            if parts is not None and self.detail:
                fits = chroma_history is not None and chroma_history.shape[1:] == parts.chroma.shares.shape[1:]
                if not fits or share_cells is None:
                    planes = chroma_history[:3] if fits else parts.chroma.shares
                    share_cells = share_error_cells(planes, parts.chroma.layout)
                frame = replace(frame, share_error=share_cells)
            partial = estimated.partial
            predicted = complete = None
            if partial is not None:
                self._settle_at_fuse(partial, frame, history)
            if partial is not None and not partial.computed.all():
                def completed() -> FrameEstimate:
                    # every band again, one crop (a run's halo rows would overwrite its computed neighbours')
                    settle.method_on_bands(partial.inp, partial.noise, np.ones_like(partial.computed), frame.image,
                                           frame.bound, frame.variance, None, self._threads)
                    partial.computed[:] = True
                    partial.rows[:] = True
                    partial.stats["completed"] = True
                    return frame

                complete = completed
                predicted = settle.band_rows(~partial.computed, frame.image.shape[0])
            noise = None
            if parts is not None and FUSE_ROWS % parts.chroma.layout.cell[0] == 0:
                # the pass updates the luminance noise's evidence and floor in place (luminance_noise)
                (h, w), cell = frame.image.shape, parts.chroma.layout.cell
                fits = spread is not None and spread.spread.shape == (h, w)
                kept = fits and spread.kept and spread.cell == cell
                noise = LuminanceNoise(spread.spread if fits else np.zeros((h, w), np.float32),
                                       spread.floor if kept else np.empty((-(-h // cell[0]), w), np.float32), cell,
                                       kept)
            fused = fuse(history, frame, self.motion_config, self.pattern.shape, inconsistency,
                         detail=self.detail, workers=self.workers, executor=self._pool,
                         predicted=predicted, complete=complete, unstable_sigmas=settle.UNSTABLE_SIGMAS,
                         noise=noise)
            if partial is not None:
                if not partial.rows.all():
                    fused = self._on_demand(partial, fused, frame, predicted, history)
                # (the pass's counts where it made them: the motion and weights not read again)
                counts = fused.row_counts
                band_motion = (settle.band_counts(fused.motion[::COUNTED_STEP]) if counts is None
                               else settle.band_sums(counts[:, 0]))
                with self._lock:  # (what the next frames' selection reads, estimate's hints too)
                    self._band_motion = [*self._band_motion, band_motion][-self.motion_config.max_history:]
                    if counts is not None:
                        self._unsettled = weakref.ref(fused.state), settle.band_sums(counts[:, 1])
                    self._last_ratio = fused.illumination_ratio
                    self._last_variance = frame.variance
                    self._in_flight.discard(partial)
                    self._fused_partials += 1
                self.last_partial = dict(partial.stats)
                method_rows = partial.stats["computed"] / partial.stats["bands"]
            image, variance_of, motion, weight = fused.image, fused.variance_of, fused.motion, fused.history
            if history is not None and history.mean.shape == image.shape:
                reset = fused.reset
            ratio, history = fused.illumination_ratio, fused.state
            if held:  # the model is not trusted yet: the history grows, the output is the frame's own
                image, variance_of, weight = _held(est, inconsistency)
        else:
            motion = np.zeros(image.shape, bool)
            if inconsistency is not None:
                image, motion = inconsistency.apply(image), inconsistency.flagged
            variance_of = OutputVariance(variance, None, inconsistency)
            weight, ratio = np.ones(image.shape, np.float32), 1.0
        luminance = None
        if parts is not None:
            if self.temporal:
                own = fuse_chroma(None, parts.chroma, weight) if held else None  # (before the fusion in place)
                made = None if estimated.chroma_of is None else estimated.chroma_of[2]
                chroma_history = fuse_chroma(chroma_history, parts.chroma, fused.history, ratio, made)
                # the fused shares differ from the last ones only on the cell rows made: the spread the fusion took
                # (of the last ones) is made again around them for the next frame, in place; else made whole then
                share_cells = (share_error_cells(chroma_history[:3], parts.chroma.layout, share_cells.cells, made)
                               if self.detail and fits and made is not None else None)
                chroma = chroma_history if own is None else own
                # the refinement weighs the fused luminance by its noise as its frames show it: a folded frame's
                # luminance is noisier than its model says, and a history averages what the model never held
                # (rows the band refresh skipped hold no estimate of this frame: their evidence stays as it was)
                skipped = (~partial.rows if partial is not None and not partial.rows.all()
                           else np.empty(0, bool))
                cell = parts.chroma.layout.cell
                if fused.noise is None:
                    evidence, floor = luminance_noise(None if spread is None else spread.spread, previous, est.image,
                                                      fused.history, weight, cell, ratio, self._threads, skipped)
                    # (a floor of the fusion's weights: the next frame's pass keeps its rows that stay)
                    spread = LuminanceNoise(evidence, floor, cell, weight is fused.history)
                else:  # made in the fusion's pass, of its weights
                    spread, floor = fused.noise._replace(kept=True), fused.noise.floor
                    if weight is not fused.history:  # the output's are others
                        floor = np.empty_like(floor)
                        noise_floor(spread.spread, weight, cell, floor, self._threads)
                luminance, variance_of, image = _refined(image, variance, floor, weight, variance_of,
                                                         parts.chroma.fused(chroma), self._threads)
                shares = chroma[:3]
            elif parts.estimate.image.ndim == 3:  # coloured in the refinement's pass (_estimate): est.image is Y
                luminance, shares, image = image, parts.chroma.shares, parts.estimate.image
            else:
                luminance = np.empty(image.shape, np.float32)  # a copy: the method's own array stays
                shares = parts.chroma.shares
                image = colour.colourise(image, parts.interpolation, self._threads, copy=luminance)
            # saturated colour's other channels from their own lattices, as a single frame's joint colour,
            # flagged by the shares that coloured the image
            colour.lattice_channels(estimated.colour_input, luminance, image, shares, parts.chroma.layout,
                                    self._threads)
        moving_fraction = float(np.count_nonzero(motion)) / motion.size
        # without fusion no frame's motion says which pixels are still: the first frame's model is final (fed
        # every frame, each would start a run of the tracker's own that is never fitted, at a tracker's cost)
        if current and self.temporal:
            self._observe_noise(estimated, reset)
        motion_ms = estimated.motion_ms + (time.perf_counter() - t1) * 1e3
        with self._lock:
            if self._generation == estimated.generation:
                self._history = history if self.temporal else None
                self._chroma = chroma_history if self.temporal and parts is not None else None
                self._white = parts.chroma.white if self.temporal and parts is not None else None
                self._spread = spread if self.temporal and parts is not None else None
                self._share_cells = share_cells if self.temporal and parts is not None else None
                self._frames = index + 1
            self._last_moving = moving_fraction
        return SequenceResult(image, motion, variance_of, est.lower_bound, weight, moving_fraction, ratio,
                              estimated.method, index, {"method": estimated.method_ms, "motion": motion_ms}, luminance,
                              reset, method_rows)


@dataclass(frozen=True)
class Estimated:
    """One frame's part of :meth:`Reconstructor.process` that needs no history (:meth:`Reconstructor.estimate`).

    Attributes:
        estimate: the method's estimate with its variance (of the luminance for a colour frame); None (and
            ``parts``, ``frame`` too) for a colour frame of the band refresh estimated behind frames in flight,
            which :meth:`Reconstructor.fuse` estimates (``Reconstructor._estimate_partial``).
        parts: a colour frame's joint parts (svelive.reconstruction.colour.Joint), or None.
        frame: what the frame contributes to the temporal fusion, or None without it.
        inconsistency: the within-frame test's finding, or None without the test.
        method: the method that made ``estimate``.
        generation: the stream's generation then (reset and method changes bump it).
        method_ms, motion_ms: wall time of the method and of the motion tests' inputs so far.
        raw: the raw frame (uint (H, W), a reference), for the stream's noise model.
        base: the stream's camera without an estimated noise model.
        trusted: whether the noise model the frame was estimated with was trusted (else its
            output is its own estimate, not the fused one).
        signal: the linearised signal above black (float32 (H, W)) of a camera with a response
            curve whose noise is estimated, else None.
        camera: the camera the frame was reconstructed with (``base`` with the noise model in use).
        noise: that noise model (source "given" where the camera gives it).
        colour_input: a colour frame's own input (its CFA channels and censoring: the lattice stage
            reads them after the fused luminance is coloured), else None.
        partial: the bands the method ran on where the stream's ``refresh`` skips some (settle.Partial), else None.
            The estimate's ``image`` holds no value on the skipped rows (fusion.fuse's ``predicted``: the
            history's mean stands for it there, and the rows of wholly skipped strips stay unwritten).
    """

    estimate: Estimate | None
    parts: colour.Joint | None
    frame: FrameEstimate | None
    inconsistency: Inconsistency | None
    method: str
    generation: int
    method_ms: float
    motion_ms: float
    raw: np.ndarray | None = None
    base: Camera | None = None
    trusted: bool = True
    signal: np.ndarray | None = None
    camera: Camera | None = None
    noise: NoiseEstimate | None = None
    colour_input: SveInput | None = None
    partial: object | None = None  # settle.Partial: the method ran on some bands only (``refresh``)
    #: a colour frame of the band refresh: (the fused chroma it kept on the cell rows it skipped or None, its
    #: selection at estimate (bool per band), bool (Hc,) the cell rows of its own chroma or None: every one)
    chroma_of: tuple | None = None


def _infinite(shape: tuple[int, int]) -> np.ndarray:
    """float32 ``shape`` of inf, read-only and of one element (a broadcast view): settle.window_rows' variance where
    a skipped row's window holds no uncensored reading (a whole frame of it, kept by the stream, was 9 MB at
    1920x1200)."""
    return np.broadcast_to(np.float32(np.inf), shape)


class _Deferred:
    """A colour frame in flight whose estimate :meth:`Reconstructor.fuse` makes (``_estimate_partial``)."""


def _chroma_rows(selected: np.ndarray, h: int, cy: int, hc: int, halo: int) -> np.ndarray:
    """bool (Hc,): the cell rows a colour frame's folded exposures read on the rows of the selected bands
    (``selected``, bool per band of a frame of ``h`` rows) and ``halo`` rows around them (the method's reach):
    the cells of cy rows those rows lie in and the one further each way (the shares' interpolation between
    cell centres)."""
    rows = np.zeros(hc, bool)
    for a, b in settle.band_rows(selected, h):
        rows[max((a - halo) // cy - 1, 0):min(-(-(b + halo) // cy) + 1, hc)] = True
    return rows


def _needs_noise(camera: Camera) -> bool:
    """Whether the camera's sensor lacks its gain or its read noise."""
    return camera.sensor.gain is None or camera.sensor.read_noise is None


def _held(est: Estimate, inconsistency: Inconsistency | None) -> tuple[np.ndarray, OutputVariance, np.ndarray]:
    """A frame's output while the noise model is not trusted: (its own estimate, float32 (H, W), with the
    within-frame test's finding applied; that estimate's variance; weights, ones float32 (H, W)), what a
    stream's first frame gives."""
    image = est.image if inconsistency is None else inconsistency.apply(est.image)
    return image, OutputVariance(est.variance, None, inconsistency), np.ones(est.image.shape, np.float32)


def own_reading_scales(sensor: Sensor) -> tuple[np.float32, np.float32]:
    """(slope, floor), float32 numbers, for per-pixel exposures (a colour frame's e', which no tile repeats):
    what the fusion multiplies 1 / e (and its square) with for the own reading's variance, 1 / (e g) and
    sigma^2 / e^2 (svelive.reconstruction.fusion.FrameEstimate, with its ``exposure``): no tables of whole
    frames written and read."""
    return np.float32(1.0 / sensor.effective_gain), np.float32(sensor.floor_variance)


def share_error(shares: np.ndarray, layout: colour.CellLayout, shape: tuple[int, int]) -> np.ndarray:
    """The relative variance of each pixel's share error, float32 (H, W) (fusion.FrameEstimate.share_error): the
    plane of :func:`share_error_cells`."""
    return share_error_cells(shares, layout).plane(shape)


def share_error_cells(shares: np.ndarray, layout: colour.CellLayout, cells: np.ndarray | None = None,
                      changed: np.ndarray | None = None) -> ShareError:
    """The relative variance of each pixel's share error by cell (fusion.ShareError: the fusion reads it so, no
    plane of it written and read).

    A colour pixel's own reading is s / (e k), k its channel's share interpolated from the cells'
    centres (``shares``, float32 (3, Hc, Wc): a stream's fused shares, else the frame's); colour that
    changes within the cells makes it k_true / k times the luminance, an error that does not average
    over frames. Its relative variance is taken as the spread of the channel's share over the 3x3
    cells around the pixel's cell: the mean of (k_j / k_0 - 1)^2 over them with the chroma's
    [1, 2, 1] / 4 weights each way, 0 where the colour is the same over the cells.

    ``cells``: float32 (3, Hc, Wc), where the spread is written (a new array where None). With ``changed`` (bool
    (Hc,)) it holds the spread of shares equal to ``shares`` on the cell rows not ``changed``, and only the cell
    rows whose 3x3 reads a changed one are made again (a still stream's fused shares change only on the cell rows
    its frame's chroma made, colour.partial_chroma).
    """
    planes = np.ascontiguousarray(shares, np.float32)
    cells = np.empty_like(planes) if cells is None else cells
    rows = np.ones(planes.shape[1], bool) if changed is None else changed.copy()
    if changed is not None:  # (a cell row reads the rows next to it, mirrored at the edges)
        rows[1:] |= changed[:-1]
        rows[:-1] |= changed[1:]
    _share_spread(planes, rows, cells)
    return ShareError(cells, layout.channels)


@kernel
def _share_spread(shares, rows, out):
    """out[c, i, j] = sum over the 3x3 cells around (i, j) (mirrored at the edges) of [1, 2, 1] / 4
    weights each way times (k_c(neighbour) / k_c(i, j) - 1)^2, on the cell rows ``rows`` (bool (Hc,)) marks."""
    n, hc, wc = shares.shape
    for c in range(n):
        k = shares[c]
        for i in range(hc):
            if not rows[i]:
                continue
            up, down = (abs(i - 1), i + 1 if i + 1 < hc else 2 * hc - 3 - i) if hc > 1 else (0, 0)
            above, middle, below, o = k[up], k[i], k[down], out[c, i]
            for j in range(1, wc - 1):  # a loop without branches, that vectorises
                o[j] = _spread_of(above, middle, below, j - 1, j, j + 1)
            if wc > 1:  # the ends, mirrored
                o[0] = _spread_of(above, middle, below, 1, 0, 1)
                o[wc - 1] = _spread_of(above, middle, below, wc - 2, wc - 1, wc - 2)
            else:
                o[0] = _spread_of(above, middle, below, 0, 0, 0)


@kernel(inline="always")
def _spread_of(above, middle, below, left, j, right):
    """:func:`_share_spread` of cell column ``j`` of three cell rows, its neighbours ``left`` and ``right``."""
    one, quarter, half = np.float32(1), np.float32(0.25), np.float32(0.5)
    inv = one / middle[j]
    a, b, d = above[left] * inv - one, above[j] * inv - one, above[right] * inv - one
    top = quarter * (a * a + d * d) + half * b * b
    a, b, d = middle[left] * inv - one, middle[j] * inv - one, middle[right] * inv - one
    centre = quarter * (a * a + d * d) + half * b * b
    a, b, d = below[left] * inv - one, below[j] * inv - one, below[right] * inv - one
    return quarter * (top + quarter * (a * a + d * d) + half * b * b) + half * centre


def luminance_noise(spread: np.ndarray | None, history: TemporalState | None, image: np.ndarray,
                    weight: np.ndarray, output_weight: np.ndarray, cell: tuple[int, int], ratio: float = 1.0,
                    workers: int | Executor = 1, skipped: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A colour stream's evidence of its luminance noise after this frame, float32 (H, W), DN^2, and the floor
    its refinement puts under the model's variance, float32 (Hc, W), made in one pass over the frame (pieces of
    whole cell rows, base.map_on over ``workers``; the result does not depend on it).

    The evidence (the stream keeps it for its next frame as ``spread``: the last frame's, None: none, or
    another size): per pixel, the mean over its frames since its last reset (the history's weights: 1 / (n - 1)
    for the n-th) of (x - m)^2 / (1 + w'), x this frame's estimate (``image``, DN), m the history's mean before
    it (times the brightness ratio, as the fusion takes it) and w' its weight; 0 where ``weight`` (this frame's,
    after fusion) is 1, or without a history of that size: no evidence yet. For a still pixel whose frames'
    errors are independent with variance v, x - m has variance v (1 + w'), so each term has mean v. A colour
    frame's luminance is the method run on readings folded by that frame's shares, whose noise (in dark cells)
    and the outliers it makes are in no model variance and differ from frame to frame (docs/motion.md).

    The floor, per cell row (``cell`` rows x cols, the cells over which the refinement takes its evidence of
    detail) and column: the evidence's mean over the pixels of the column's cell that have evidence
    (``output_weight`` < 1). The refinement's variance (colour.refine's ``floor``) is the larger of the model's
    and the floor where ``output_weight`` < 1, the model's where it is 1 (a reset pixel, or an output that is
    the frame's own: no history to judge).

    ``skipped``: bool (H,), rows whose ``image`` is not this frame's estimate (the band refresh kept the history's
    mean there), or of no rows: there a pixel's evidence stays the last frame's (0 where ``weight`` is 1).
    (A stream's fusion makes the two in its pass instead, in place and bit for bit:
    svelive.reconstruction.fusion.LuminanceNoise.)
    """
    evidence = history is not None and history.mean.shape == image.shape
    out = np.empty(image.shape, np.float32)
    if not evidence:
        mean = old_weight = old = image  # (not read)
    else:
        mean, old_weight = history.mean, history.weight
        old = spread if spread is not None and spread.shape == image.shape else out
        if old is out:  # the first frame with a history: none before it, zeros updated in place
            out[:] = 0
    scale = np.float32(ratio) if abs(ratio - 1.0) > RATIO_TOLERANCE else np.float32(1)
    cy, cx = cell
    floor = np.empty((-(-image.shape[0] // cy), image.shape[1]), np.float32)
    arrays = [np.ascontiguousarray(a) for a in (image, mean, old_weight, weight, old, output_weight)]
    rows_skipped = np.zeros(image.shape[0], bool) if skipped is None or not skipped.size else skipped

    def piece(rows: slice) -> None:
        _noise_rows(*(a[rows] for a in arrays), scale, evidence, False, cy, cx, out[rows],
                    floor[rows.start // cy:-(-rows.stop // cy)], rows_skipped[rows])

    map_on(workers, piece, _pieces(image.shape[0], cy))
    return out, floor


@kernel
def _noise_rows(image, mean, old_weight, weight, old, output_weight, scale, evidence, made, cy, cx, spread, floor,
                skipped):
    """spread, floor = :func:`luminance_noise`'s of whole cell rows (row 0 a cell row's first; ``old`` may be
    ``spread``; with ``made``, ``spread`` holds the evidence already, and only ``output_weight`` is read beside it),
    each cell row's spread summed per column while its rows are in cache, then its cells' means spread over the
    cell row's row of ``floor`` (loops that vectorise)."""
    one, zero = np.float32(1), np.float32(0)
    h, w = spread.shape
    total, count = np.empty(w, np.float32), np.empty(w, np.float32)
    for r0 in range(0, h, cy):
        r1 = min(r0 + cy, h)
        total[:] = zero
        count[:] = zero
        for r in range(r0, r1):
            s, wo = spread[r], output_weight[r]
            if made:
                for x in range(w):
                    total[x] += s[x]
                    count[x] += one if wo[x] < one else zero
            elif evidence and skipped[r]:  # (the band refresh's kept rows: no new evidence)
                wt, o = weight[r], old[r]
                for x in range(w):
                    value = o[x] if wt[x] < one else zero
                    s[x] = value
                    total[x] += value
                    count[x] += one if wo[x] < one else zero
            elif evidence:
                x_, m, ow, wt, o = image[r], mean[r], old_weight[r], weight[r], old[r]
                for x in range(w):
                    value = noise_evidence(x_[x], m[x], ow[x], wt[x], o[x], scale)
                    s[x] = value
                    total[x] += value
                    count[x] += one if wo[x] < one else zero
            else:
                for x in range(w):
                    s[x] = zero
                    count[x] += one if wo[x] < one else zero
        cell_means(total, count, cx, floor[r0 // cy])


def noise_floor(spread: np.ndarray, output_weight: np.ndarray, cell: tuple[int, int], floor: np.ndarray,
                workers: int | Executor = 1, rows: np.ndarray | None = None) -> None:
    """floor = :func:`luminance_noise`'s of its evidence ``spread`` (float32 (H, W), DN^2, made already) and
    ``output_weight`` (float32 (H, W)), float32 (Hc, W), in place: every cell row (pieces over ``workers``), or
    the cell rows ``rows`` (intp) alone."""
    (h, _), (cy, cx) = spread.shape, cell
    no_rows = np.empty(0, bool)

    def piece(part: slice) -> None:
        s, wo = spread[part], output_weight[part]  # (the evidence's own inputs: not read)
        _noise_rows(s, s, s, wo, s, wo, np.float32(1), True, True, cy, cx, s,
                    floor[part.start // cy:-(-part.stop // cy)], no_rows)

    if rows is None:
        map_on(workers, piece, _pieces(h, cy))
    else:
        for i in rows.tolist():
            piece(slice(i * cy, min(i * cy + cy, h)))


def fuse_chroma(history: np.ndarray | None, chroma: colour.Chroma, weight: np.ndarray,
                ratio: float = 1.0, rows: np.ndarray | None = None) -> np.ndarray:
    """A colour stream's chroma after this frame, float32 (5, Hc, Wc): the shares k_R, k_G, k_B,
    the coarse luminance and its variance (svelive.reconstruction.colour.Chroma).

    Per cell the weight is the largest history weight (1 / n, 1 where reset) of the pixels of its
    3x3 cells, whose readings its chroma comes from: the shares and the coarse luminance (its
    history times ``ratio``, the brightness ratio the luminance's fusion divided out) take the
    running mean with it, the variance is this frame's times it (as the luminance's). This frame's
    alone without a history of that shape.

    ``rows``: bool (Hc,), the cell rows of the frame's own chroma (colour.partial_chroma), or None: every one;
    the others keep the history's cells (its coarse luminance times ``ratio``): partial_chroma's of this
    ``history`` holds them there already.

    With a history, the chroma's planes (colour.Chroma.planes) become the fused chroma, in place: the frame's own
    chroma is not kept (partial_chroma's history cells are not copied a second time, and no array is allocated).
    """
    (cy, cx), (hc, wc) = chroma.layout.cell, chroma.shares.shape[1:]
    if history is None or history.shape != (5, hc, wc):
        return np.concatenate([chroma.shares, chroma.coarse])
    out = chroma.planes
    if out is None and rows is not None:
        raise ValueError("a chroma made on some cell rows is partial_chroma's, one (5, Hc, Wc) array")
    if out is None:  # (a chroma of arrays of their own)
        out = np.concatenate([chroma.shares, chroma.coarse])
    box = np.ones((3, 3), np.uint8)
    cells = np.empty((hc, wc), np.float32)  # (with ``rows``, the rows not made are not read)
    if rows is None:
        _cell_maximum(weight, cy, cx, cells)
        cells = cv2.dilate(cells, box, borderType=cv2.BORDER_REFLECT_101)
    else:  # the cell rows made, each run from a crop of one more cell row each way (the 3x3's reach)
        for a, b in settle.runs(rows):
            lo, hi = max(a - 1, 0), min(b + 1, hc)
            crop = np.empty((hi - lo, wc), np.float32)
            _cell_maximum(weight[lo * cy:hi * cy], cy, cx, crop)
            cells[a:b] = cv2.dilate(crop, box, borderType=cv2.BORDER_REFLECT_101)[a - lo:b - lo]
    _running_chroma(history, cells, np.float32(ratio), np.ones(hc, bool) if rows is None else rows, out)
    return out


def _refined(luminance: np.ndarray, variance: np.ndarray, floor: np.ndarray, weight: np.ndarray,
             variance_of: OutputVariance, fused: colour.Chroma,
             workers: int | Executor = 1) -> tuple[np.ndarray, Callable[[], np.ndarray], np.ndarray]:
    """A colour stream's output luminance (the fused one refined against the fused coarse luminance,
    with v_Y the frame's ``variance`` at least ``floor`` (:func:`luminance_noise`'s) times the history
    weight), the variance of that on demand, and that luminance coloured with the fused shares, float32
    (H, W, 3) (colour.colourise's, made in the refinement's pass)."""
    inter = colour.interpolation(fused, coarse=True)
    cell = fused.layout.cell
    rgb = np.empty((*luminance.shape, 3), np.float32)
    refined = colour.refine(luminance, variance, inter, cell, weight=weight, floor=floor, rgb=rgb, workers=workers)

    def refined_variance() -> np.ndarray:
        out = np.empty(luminance.shape, np.float32)
        # (``inter`` holds the fused cells and makes their rows at every column as the refinement's pieces read
        # them: a published frame that holds this closure holds no (5, Hc, W) planes)
        colour.refine(luminance, variance_of(), inter, cell, out_variance=out, new_variance=True)
        return out

    return refined, refined_variance, rgb


@kernel
def _cell_maximum(weight, cy, cx, out):
    """out (Hc, Wc) = the largest of ``weight`` (H, W) over each cell of cy x cx pixels: the cell
    rows' largest per column first (a loop that vectorises), then each cell's columns."""
    h, w = weight.shape
    column = np.empty(w, np.float32)
    for i in range(out.shape[0]):
        r0, r1 = i * cy, min(i * cy + cy, h)
        column[:] = weight[r0]
        for r in range(r0 + 1, r1):
            row = weight[r]
            for x in range(w):
                column[x] = max(column[x], row[x])
        o, start = out[i], 0
        if cx == 2:  # cells of two columns spelt out: a loop that vectorises
            start = w // 2
            for j in range(start):
                o[j] = max(column[2 * j], column[2 * j + 1])
        for j in range(start, o.size):
            top = column[j * cx]
            for x in range(j * cx + 1, min(j * cx + cx, w)):
                top = max(top, column[x])
            o[j] = top


@kernel
def _running_chroma(history, weight, ratio, rows, out):
    """out (5, Hc, Wc): this frame's chroma in (the shares, the coarse luminance and its variance), the fused out,
    in place: history + weight (new - history) per cell for the shares (planes 0-2), the same with the history
    times ``ratio`` for the coarse luminance (3), new times weight for its variance (4). Cell rows not in ``rows``
    (bool (Hc,)) hold the history already (partial_chroma's): only their coarse luminance is multiplied, by
    ``ratio`` (not where it is 1). (Each loop reads and writes ``out`` alone: with this frame's planes as views of
    it read beside, LLVM's alias check fell to scalar loops.)"""
    for c in range(5):
        scale = ratio if c == 3 else np.float32(1.0)
        for i in range(weight.shape[0]):
            a, w, o = history[c, i], weight[i], out[c, i]
            if not rows[i]:
                if scale != np.float32(1.0):
                    for j in range(o.size):
                        o[j] = a[j] * scale
            elif c == 4:
                for j in range(o.size):
                    o[j] = o[j] * w[j]
            else:
                for j in range(o.size):
                    o[j] = a[j] * scale + (o[j] - a[j] * scale) * w[j]


def reconstruct_sequence(frames: Iterable[np.ndarray], pattern: Pattern | str, **kwargs) -> Iterator[SequenceResult]:
    """Reconstruct an iterable of raw frames (arrays, or objects with a ``raw`` array such as svelive.Frame).

    Keyword arguments are those of :class:`Reconstructor`. Yields one SequenceResult per frame, lazily.
    """
    reconstructor = Reconstructor(pattern, **kwargs)
    for frame in frames:
        yield reconstructor.process(frame)


#: Frames of a stream's start that give its noise model where the camera does not (:func:`stream_noise`):
#: as in each run of a stream's model (svelive.noise.StreamNoise), the first frame's own samples,
#: then the differences of the pixels found static in the next two (three frames group them without bias).
NOISE_FRAMES = 3


def stream_noise(frames: Sequence[np.ndarray | Frame], camera: Camera, *, method: str | None = None,
                 exposure_timing: str = "mask") -> NoiseEstimate:
    """The noise model of a stream from its first frames, for a camera that does not give its gain or read noise.

    The model a :class:`Reconstructor` of the camera estimates from these frames (:attr:`Reconstructor.noise`,
    svelive.noise.StreamNoise, one run of all of them): the first frame's single-frame estimate, then a
    :class:`svelive.noise.NoiseTracker` fed the differences of the pixels the motion tests found static in
    each next frame, as the live service does. With :data:`NOISE_FRAMES` frames of a still scene both values
    come within 15 % in about 94 % of the shared images' runs, against 66 % from one frame (docs/noise.md).

    Args:
        frames: the stream's first frames (uint (H, W) raw arrays, or Frames), in order; any number >= 1
            (one frame gives the single-frame estimate).
        camera: the camera of every frame (a Frame's own camera is not read).
        method, exposure_timing: the Reconstructor's, for the motion tests.

    Returns:
        The estimate; the camera's own values, source "given", when it gives both. A value the camera
        gives is kept by ``estimate.apply(camera.sensor)``.
    """
    sensor = camera.sensor
    if sensor.gain is not None and sensor.read_noise is not None:
        return NoiseEstimate.given(sensor)
    if len(frames) == 0:
        raise SveliveError("no frame to estimate the noise model from")
    schedule = NoiseSchedule(run_frames=max(len(frames), 2), refit_every=0)
    with Reconstructor(camera, method=method, temporal=True, exposure_timing=exposure_timing,
                       noise_schedule=schedule) as stream:
        for frame in frames:
            stream.process(camera.check(np.asarray(getattr(frame, "raw", frame))))
        return stream.noise
