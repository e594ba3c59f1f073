"""The noise model of one stream, refined frame by frame (:class:`NoiseTracker`).

The difference of two consecutive frames at static pixels removes the scene altogether (variance
``2 (s / g + R)``); those samples are pooled with every frame's single-frame samples, over a bounded
history, and the line is refitted.
"""

from __future__ import annotations

import hashlib
from collections import deque
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from svelive.core.errors import SveliveError
from svelive.core.sensor import Sensor
from svelive.memory import outside_heap
from svelive.noise.cancellation import cancellation_fit
from svelive.noise.frame import _preferred, frame_samples
from svelive.noise.inputs import _fixed, _high_level, _signal_of
from svelive.noise.model import QUANTISATION_VARIANCE, EstimatorConfig, LineFit, NoiseEstimate, NoiseSamples
from svelive.noise.prior import estimate_from_fit
from svelive.noise.stats import bin_samples, fit_line
from svelive.noise.temporal import temporal_samples, triple_samples

if TYPE_CHECKING:  # the Camera is only read here (its pattern, colour filter and sensor)
    from svelive.core.camera import Camera


class NoiseTracker:
    """The noise model of one stream, refined frame by frame.

    Static pixels between consecutive frames give texture-free samples (their difference removes
    the scene); three consecutive frames give them without the pair's correction for binning by a
    noisy signal (:func:`triple_samples`), and are used alone once there are enough of them. Once
    the recent frames hold enough temporal samples (``temporal_enough``) the line is fitted
    to those alone, else to them pooled with the single-frame samples of the recent frames (which
    texture can bias); without any temporal samples (a moving camera, no static mask) that line is
    weighed against the recent frames' texture-cancelled fits (:func:`cancellation_fit`, combined by
    inverse variance) as :func:`estimate_from_frame` does. A given gain or read noise in the camera is
    kept. Not thread-safe: one per stream.

    :meth:`update` adds a frame and fits; :meth:`add` only adds it, and :meth:`fit` fits what was
    added. The pool is fitted only when what it holds changed, and a fit that adding a frame needs
    (the clip margins of temporal samples, the start of the texture-cancelled fit) is the one
    :meth:`update` would have made after the frame before: ``add, add, update`` gives the estimate
    of ``update, update, update`` to the bit, with a third of the fits where the pool is unchanged
    between runs (the service's runs of three frames once temporal samples suffice).
    """

    def __init__(self, history: int = 16, config: EstimatorConfig = EstimatorConfig(),
                 temporal_samples_per_frame: int = 50_000, temporal_enough: int = 20_000) -> None:
        self.config = config
        self.temporal_per_frame = temporal_samples_per_frame
        self.temporal_enough = temporal_enough
        self._frame_parts: deque[NoiseSamples] = deque(maxlen=history)
        self._temporal_parts: deque[NoiseSamples] = deque(maxlen=history)
        self._joint_fits: deque[LineFit] = deque(maxlen=history)
        self._triple_parts: deque[NoiseSamples] = deque(maxlen=history)
        self._previous: np.ndarray | None = None
        self._before_previous: np.ndarray | None = None  # the frame before it, when it was static to it
        self._previous_static: np.ndarray | None = None  # the mask that related the two
        self._rested: bytes | None = None  # the digest of the last frame added before :meth:`rest`
        self._estimate: NoiseEstimate | None = None
        self._camera_key: tuple | None = None
        self._sensor: Sensor | None = None  # of the frames added since the last reset
        self._line_of: tuple[tuple, LineFit | None, int] | None = None  # (pool, its line, samples)
        self._estimate_of: tuple | None = None  # what self._estimate was fitted to

    @property
    def estimate(self) -> NoiseEstimate | None:
        """The estimate of the last fit (:meth:`update` or :meth:`fit`), None before the first."""
        return self._estimate

    def reset(self) -> None:
        """Forget every frame (the camera changed)."""
        self._frame_parts.clear()
        self._temporal_parts.clear()
        self._joint_fits.clear()
        self._triple_parts.clear()
        self._previous = self._before_previous = self._previous_static = None
        self._rested = None
        self._estimate = None
        self._camera_key = None
        self._sensor = None
        self._line_of = self._estimate_of = None

    def update(self, raw: np.ndarray, camera: Camera, static_mask: np.ndarray | None = None, *,
               signal: np.ndarray | None = None) -> NoiseEstimate:
        """Add one frame (:meth:`add`) and return the refined estimate (:meth:`fit`)."""
        self.add(raw, camera, static_mask, signal=signal)
        return self.fit()

    def add(self, raw: np.ndarray, camera: Camera, static_mask: np.ndarray | None = None, *,
            signal: np.ndarray | None = None) -> None:
        """Add one frame's samples without fitting the pool (but where the samples need the current fit).

        Args:
            raw: uint (H, W) raw frame as delivered.
            camera: its camera; a change of pattern, colour filter, levels or shape starts over.
            static_mask: bool (H, W), pixels known not to have changed since the previous frame (e.g.
                the motion test's static pixels); None gives no temporal samples (a moving camera
                would bias them), only the single-frame ones. A frame equal to the previous one adds
                nothing.
            signal: the linear signal above black when the camera has a response (see :func:`estimate_from_frame`).
        """
        sensor = camera.sensor
        key = (str(camera.pattern), None if camera.cfa is None else str(camera.cfa), sensor.black_level,
               sensor.white_level, sensor.gain, sensor.read_noise, np.shape(raw))
        if key != self._camera_key:
            self.reset()
            self._camera_key = key
        if sensor.gain is not None and sensor.read_noise is not None:
            self._sensor = sensor
            return
        source, offset, floor = _signal_of(raw, camera, signal)
        # the tracker's own copy (kept as the previous frame), made once, outside the heap (svelive.memory)
        sig = outside_heap(np.shape(source), np.float32)
        np.copyto(sig, source, casting="unsafe")
        sig -= np.float32(offset)
        if (np.array_equal(sig, self._previous) if self._previous is not None
                else self._rested is not None and _digest(sig) == self._rested):
            # the frame before delivered again (a buffer sent twice, a short loop of recorded frames): its
            # differences would say the sensor has no temporal noise, and its own samples are counted already
            return
        static = None if static_mask is None else np.asarray(static_mask, bool)
        if static is not None and static.shape != sig.shape:
            raise SveliveError(f"static mask has shape {static.shape} but the frame {sig.shape}")
        if static is not None and self._previous is not None:
            current = self.fit() if self._sensor is not None else estimate_from_fit(None, sensor, 0)
            model = (1.0 / current.gain, current.read_noise**2 + QUANTISATION_VARIANCE)
            if self._before_previous is not None:
                self._triple_parts.append(triple_samples(self._before_previous, self._previous, sig,
                                                         static & self._previous_static, floor,
                                                         _high_level(sensor), model, self.temporal_per_frame))
            else:
                self._temporal_parts.append(temporal_samples(self._previous, sig, static, floor,
                                                             _high_level(sensor), model, self.temporal_per_frame,
                                                             camera.period))
        self._sensor = sensor
        config = self.config
        temporal = self._temporal_size()
        if temporal < self.temporal_enough:
            samples, _ = frame_samples(raw, camera, signal=sig, config=config)
            self._frame_parts.append(samples)
        # temporal samples are texture-free: with any, the pooled line is the better evidence
        if config.cancellation and sensor.gain is None and temporal == 0:
            frame_joint = cancellation_fit(sig, 0.0, floor, camera, config, start=self._line()[0])
            if frame_joint is not None:
                self._joint_fits.append(frame_joint)
        if static is not None and self._previous is not None:
            self._before_previous, self._previous_static = self._previous, static
        else:
            self._before_previous = self._previous_static = None
        self._previous = sig
        self._rested = None

    def rest(self) -> None:
        """Drop the frames kept for the next frame's samples, keeping a digest of the last one: for a pause in
        the frames added (a stream's tracker reads runs of three frames every 64 to 512, ``svelive.noise.StreamNoise``),
        after which the next frame comes without a static mask. Such a frame reads no frame before it but to
        tell whether it is the last one again (then it adds nothing, as without the pause); with a static mask
        it would have given temporal samples from the frame before, which are now not taken."""
        if self._previous is not None:
            self._rested = _digest(self._previous)
        self._previous = self._before_previous = self._previous_static = None

    def fit(self) -> NoiseEstimate:
        """The estimate from every frame added (refitted only when the pool changed since the last fit)."""
        sensor = self._sensor
        if sensor is None:
            raise SveliveError("no frame added to the noise tracker")
        if sensor.gain is not None and sensor.read_noise is not None:
            self._estimate = NoiseEstimate.given(sensor)
            return self._estimate
        config = self.config
        with_joint = config.cancellation and sensor.gain is None and self._temporal_size() == 0
        pool, joints = self._pool()[0], tuple(self._joint_fits) if with_joint else ()
        if self._estimate_of is not None and _same(self._estimate_of, (pool, joints)):
            return self._estimate
        fit, count = self._line()
        joint = _combined(list(joints)) if with_joint else None
        if joint is not None and _preferred(fit, joint, config) is joint:
            fit, count = joint, int(joint.bins_n.sum())
        self._estimate = estimate_from_fit(fit, sensor, count)
        self._estimate_of = (pool, joints)
        return self._estimate

    def _temporal_size(self) -> int:
        """How many temporal samples the pool holds: three frames' alone once enough, else with the pairs' (counted,
        not joined: a full pool's join is a copy of 16 runs' samples, 13 MB, at every frame added)."""
        return sum(p.size for p in self._temporal_list())

    def _temporal_list(self) -> list[NoiseSamples]:
        triples = list(self._triple_parts)
        if sum(p.size for p in triples) >= self.temporal_enough:
            return triples
        return [*triples, *self._temporal_parts]

    def _pool(self) -> tuple[tuple[NoiseSamples, ...], bool]:
        """The parts the line is fitted to, and whether they are temporal alone (binned as such)."""
        temporal = self._temporal_list()
        if sum(p.size for p in temporal) >= self.temporal_enough:
            return tuple(temporal), True
        return (*self._frame_parts, *temporal), False

    def _line(self) -> tuple[LineFit | None, int]:
        """The line fitted to the pool and its sample count, fitted again only when the pool changed."""
        parts, only_temporal = self._pool()
        if self._line_of is not None and _same(self._line_of[0], (parts, only_temporal)):
            return self._line_of[1], self._line_of[2]
        pooled = NoiseSamples.join(list(parts))
        fit = fit_line(*bin_samples(pooled, self.config, temporal=only_temporal), **_fixed(self._sensor),
                       outlier_tolerance=self.config.outlier_tolerance)
        self._line_of = ((parts, only_temporal), fit, pooled.size)
        return fit, pooled.size


def _digest(signal: np.ndarray) -> bytes:
    """A digest of a float32 frame's shape and bits, to tell a frame delivered again without keeping the frame."""
    digest = hashlib.blake2b(repr(signal.shape).encode(), digest_size=32)
    digest.update(np.ascontiguousarray(signal))
    return digest.digest()


def _same(a: object, b: object) -> bool:
    """Whether two nests of tuples hold the very same objects (identity, not equality: arrays)."""
    if isinstance(a, tuple) and isinstance(b, tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return a is b


def _combined(fits: list[LineFit]) -> LineFit | None:
    """Texture-cancelled fits of several frames as one: slope and intercept weighted by the inverse of
    their variances, the covariance that of the weighted mean (the frames' noise is independent; the
    texture the fits removed is not, and is no part of their covariance). None for no fits."""
    if not fits:
        return None
    if len(fits) == 1:
        return fits[0]
    out = []
    for k in (0, 1):
        var = np.array([max(f.cov[k, k], 1e-300) for f in fits])
        values = np.array([(f.slope, f.intercept)[k] for f in fits])
        w = 1.0 / var
        out.append((float(np.sum(w * values) / np.sum(w)), 1.0 / float(np.sum(w))))
    first = fits[0]
    return replace(first, slope=out[0][0], intercept=out[1][0], cov=np.diag([out[0][1], out[1][1]]),
                   bins_n=np.concatenate([f.bins_n for f in fits]), bins_t=np.concatenate([f.bins_t for f in fits]),
                   bins_v=np.concatenate([f.bins_v for f in fits]),
                   inlier=np.concatenate([f.inlier for f in fits]))
