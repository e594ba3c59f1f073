"""Reprocessing a recording: frames to EXR files, in this process or on a Dask cluster; and any other
stream of frames, in order (:func:`run_stream`). Every frame is written by :func:`write_result`.

A recording is read by frame index (replay.RecordingReader, constant-time seek), so
any process that sees the file can reconstruct any range of it: the client plans
the work, the workers read the frames themselves (no raw frame goes through the
scheduler) and write ``frame_NNNNNN.exr`` (NNNNNN: the frame's index in the
recording) atomically (svelive.exr.write_exr), so an interrupted run is resumed by
running it again: a frame whose EXR opens and holds the expected channels and size
is skipped.

Which frames may go to which worker:

- Single-frame methods on a monochrome recording (or a fixed white balance):
  every frame is independent, one task each.
- Temporal fusion is a recursion over frames: a pixel's history is the running mean
  ``m <- m + w (x - m)`` with ``w = 1 / min(n, max_history)`` frames since its last
  reset (svelive.reconstruction.fusion). A chunk [start, stop) is therefore run from
  ``start - K`` with an empty history, and its first K frames only warm the history
  up. Once a static pixel's weight reaches 1 / max_history in both runs (after
  max_history frames) the two histories differ by a factor (1 - 1 / max_history)
  less each frame, so after K = max_history + ceil(24 ln 2 / -ln(1 - 1 / max_history))
  frames (133 with max_history 8) the difference is below float32 rounding
  (2^-24 of the difference at the start). A pixel that the motion test resets is
  exact from then on.
- The automatic white balance of a colour recording is a first-order low-pass
  filter over frame time (svelive.whitebalance.WhiteBalancer, time constant
  ``adapt_s``), measured on every frame ``measure_s`` after the previous
  measurement: a colour chunk starts at a frame that the sequential run measures
  too (the measurement times follow from the timestamps alone) and at least
  ``adapt_s * 24 ln 2`` seconds of frame time (16.6 s) before ``start``, or at a
  gap longer than ``reset_after_s``, where the filter restarts exactly.
- The history cannot be reset on demand without changing the output, and a motion
  test whose statistic sits within rounding of its threshold can decide otherwise
  in a run whose history differs by rounding (a colour stream with much motion
  kept doing so for ~170 frames): the warm-up alone guarantees nothing. So every
  chunk that starts cold is checked (:func:`execute`): its state before its first
  frame must equal the state the chunk before it ends with (:func:`compare_states`:
  the same resets, fused values within STATE_RTOL), or it runs again with twice
  the warm-up, at most from frame 0.

docs/reprocessing.md has the figures.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from svelive.core.camera import Camera
from svelive.core.errors import SveliveError
from svelive.core.frame import Frame
from svelive.frame_exr import FrameInfo, write_frame_exr
from svelive.noise import NoiseEstimate
from svelive.reconstruction.config import MotionConfig
from svelive.whitebalance import ColourSettings, WhiteBalance, WhiteBalancer

#: The pip extra that installs Dask (pyproject.toml's optional dependencies).
EXTRA = "cluster"
INSTALL = f'pip install "svelive[{EXTRA}]"  (or: pip install "dask[distributed]")'

#: float32's relative rounding: warm-ups run until an initial difference has shrunk below it.
FLOAT32_BITS = 24


@dataclass(frozen=True)
class Job:
    """What to reprocess, as every worker needs it (small and picklable).

    Attributes:
        recording: path of the .sverec file, as the workers see it.
        output: the output directory, as the workers see it.
        method: single-frame method, or None for the Reconstructor's default.
        temporal: fuse frames over time.
        timing: exposure timing, ``mask`` or ``integration``.
        source_options: options of the ``replay:`` source (pattern, cfa, bits,
            black_level, white_level) that override the recorded camera.
        gain, read_noise: override the sensor's (electrons per DN; DN).
        noise: the noise model estimated from the recording's first frames (:func:`with_stream_noise`),
            whose values the camera takes where neither it nor ``gain``/``read_noise`` gives them; it is
            named in every EXR. None: the camera's own values, else the fixed defaults.
        colour: the colour output settings (white balance, matrix, output space).
        half: write half floats.
        motion: the motion tests' thresholds (max_history sets the warm-up).
        frames: only the first this many frames of the recording (None: all).
    """

    recording: str
    output: str
    method: str | None = None
    temporal: bool = True
    timing: str = "mask"
    source_options: dict[str, Any] = field(default_factory=dict)
    gain: float | None = None
    read_noise: float | None = None
    noise: NoiseEstimate | None = None
    colour: ColourSettings = field(default_factory=ColourSettings)
    half: bool = False
    motion: MotionConfig = field(default_factory=MotionConfig)
    frames: int | None = None


@dataclass(frozen=True)
class Chunk:
    """Frames [start, stop) to write, reconstructed from ``first`` (<= start) on: frames
    first..start-1 only warm the stream's state up."""

    first: int
    start: int
    stop: int

    @property
    def warmup(self) -> int:
        return self.start - self.first


@dataclass(frozen=True)
class ChunkResult:
    """What a task did: frames written, already complete (skipped), damaged in the recording, and
    frames reconstructed (warm-up included) in ``seconds`` of wall time.

    ``start_state`` and ``end_state`` are the stream's state (:func:`stream_state`) before frame
    ``start`` and after frame ``stop - 1``, None for a stream without state; ``staged``: the
    EXRs were written to :func:`staging_dir` and wait for the chunk's check."""

    written: tuple[int, ...]
    complete: tuple[int, ...]
    damaged: tuple[int, ...]
    reconstructed: int
    seconds: float
    start_state: dict[str, Any] | None = field(default=None, repr=False)
    end_state: dict[str, Any] | None = field(default=None, repr=False)
    staged: bool = False

    def without_states(self) -> ChunkResult:
        """This result without the (large) states."""
        return replace(self, start_state=None, end_state=None)


def frame_path(output: str | Path, index: int) -> Path:
    """The EXR of recording frame ``index``."""
    return Path(output) / f"frame_{index:06d}.exr"


def fusion_warmup(motion: MotionConfig, bits: int = FLOAT32_BITS) -> int:
    """Frames after which a fused history started empty agrees with one started earlier to 2^-bits
    (module docstring): max_history + ceil(bits ln 2 / -ln(1 - 1 / max_history))."""
    m = int(motion.max_history)
    if m <= 1:
        return 1  # a history of one frame is the frame itself
    return m + math.ceil(bits * math.log(2) / -math.log1p(-1.0 / m))


def white_balance_chain(times_ns: np.ndarray, balancer: WhiteBalancer) -> tuple[np.ndarray, np.ndarray]:
    """(measured, restarted), bool (N,): the frames at which ``balancer`` (automatic) measures, and
    those at which its filter restarts, for frames at ``times_ns`` (int64 (N,)).

    The rule of svelive.whitebalance.WhiteBalancer.update: a frame is measured unless it comes
    less than ``measure_s`` after the last measured one; the filter restarts at the first
    frame and after a gap of more than ``reset_after_s`` (or backwards in time). It depends
    on the timestamps only.
    """
    measured = np.zeros(len(times_ns), bool)
    restarted = np.zeros(len(times_ns), bool)
    last: int | None = None
    for i, t in enumerate(times_ns.tolist()):
        dt = None if last is None else (t - last) / 1e9
        if dt is not None and 0 <= dt < balancer.measure_s:
            continue
        measured[i] = True
        restarted[i] = dt is None or not 0 <= dt <= balancer.reset_after_s
        last = t
    return measured, restarted


@dataclass(frozen=True)
class Plan:
    """The chunks of a run and what the plan was made from.

    Attributes:
        chunks: the work, in frame order.
        frames: frames of the recording considered.
        complete: frames whose EXR was complete already (skipped).
        warmup: the fusion warm-up K in frames (0 without temporal fusion).
        colour_warmup_s: frame time the white balance warms up over (0 when not needed).
    """

    chunks: tuple[Chunk, ...]
    frames: int
    complete: tuple[int, ...]
    warmup: int
    colour_warmup_s: float


def plan(todo: Iterable[int], frames: int, *, warmup: int, workers: int, times_ns: np.ndarray | None = None,
         balancer: WhiteBalancer | None = None, colour_warmup_s: float = 0.0, per_frame: bool = True) -> list[Chunk]:
    """Split the frame indices ``todo`` (sorted, in 0..frames-1) into chunks.

    Without warm-up (independent frames) each frame is a chunk (``per_frame``; else each
    run of consecutive frames, for one process). With one, each run of
    consecutive missing frames is split into at most ``workers`` chunks of equal length,
    fewer when a chunk would be shorter than its warm-up (it would cost more than it
    saves), each started ``warmup`` frames early, and earlier still for the white
    balance (``balancer``, ``times_ns``, ``colour_warmup_s``: see the module docstring).
    """
    todo = sorted(todo)
    if not todo:
        return []
    if warmup == 0 and balancer is None and per_frame:
        return [Chunk(i, i, i + 1) for i in todo]
    runs: list[tuple[int, int]] = []
    for i in todo:
        if runs and runs[-1][1] == i:
            runs[-1] = (runs[-1][0], i + 1)
        else:
            runs.append((i, i + 1))
    if warmup == 0 and balancer is None:
        return [Chunk(a, a, b) for a, b in runs]
    measured = restarted = None
    if balancer is not None and times_ns is not None:
        measured, restarted = white_balance_chain(times_ns, balancer)
    chunks = []
    for a, b in runs:
        n = b - a
        count = max(1, min(workers, n // max(warmup, 1)))
        edges = [a + (n * k) // count for k in range(count + 1)]
        for start, stop in zip(edges[:-1], edges[1:]):
            first = max(0, start - warmup)
            if measured is not None and first > 0:
                first = _colour_start(first, start, times_ns, measured, restarted, colour_warmup_s)
            chunks.append(Chunk(first, start, stop))
    return chunks


def _colour_start(first: int, start: int, times_ns: np.ndarray, measured: np.ndarray, restarted: np.ndarray,
                  span_s: float) -> int:
    """The latest frame <= ``first`` that the white balance measures in the sequential run and that
    is a restart of its filter or ``span_s`` of frame time before frame ``start``; 0 if none."""
    for i in range(first, 0, -1):
        if measured[i] and (restarted[i] or (times_ns[start] - times_ns[i]) / 1e9 >= span_s):
            return i
    return 0


# ----- the work of one task (runs on a worker) -----------------------------------------------
def job_camera(job: Job) -> tuple[Camera, Any]:
    """(the camera frames are reconstructed with, the open RecordingReader): the recorded camera with
    the job's source options (as the ``replay:`` source applies them) and gain/read-noise overrides."""
    from replay import RecordingReader
    from svelive.capture import open_source

    source = open_source(f"replay:{job.recording}", **job.source_options)  # checks the file and the options
    camera = source.camera
    camera.require_pattern()
    if job.gain is not None or job.read_noise is not None:
        camera = camera.replace(sensor=camera.sensor.with_noise(job.gain, job.read_noise))
    if job.noise is not None:
        camera = camera.replace(sensor=job.noise.apply(camera.sensor))
    return camera, RecordingReader(job.recording, warn=False)


def with_stream_noise(job: Job) -> Job:
    """``job`` with ``noise`` estimated from the recording's first intact frames (up to NOISE_FRAMES of the
    frames it covers; :func:`svelive.reconstruction.stream.stream_noise`) when its camera gives no gain or
    read noise; ``job`` itself otherwise. Done once, before the chunks are planned, so that every worker and
    every resumed run reconstructs with the same model."""
    from replay import CorruptFrameError
    from svelive.reconstruction.stream import NOISE_FRAMES, stream_noise

    camera, reader = job_camera(job)
    if camera.sensor.gain is not None and camera.sensor.read_noise is not None:
        reader.close()
        return job
    frames = []
    with reader:
        for i in range(len(reader) if job.frames is None else min(job.frames, len(reader))):
            try:
                frames.append(reader.read(i).raw)
            except CorruptFrameError:
                continue
            if len(frames) == NOISE_FRAMES:
                break
    if not frames:
        return job  # no intact frame: nothing to reconstruct either, which the run reports
    noise = stream_noise(frames, camera, method=job.method, exposure_timing=job.timing)
    return replace(job, noise=noise)


def stateful(job: Job, camera: Camera) -> bool:
    """True when a frame's output depends on the frames before it: temporal fusion, or a colour
    camera's automatic white balance."""
    return job.temporal or (camera.cfa is not None and job.colour.auto)


def expected_channels(camera: Camera) -> set[str]:
    """The channel names of an output EXR for ``camera``."""
    return ({"Y"} if camera.cfa is None else {"R", "G", "B"}) | {"confidence", "motion"}


def is_complete(path: Path, shape: tuple[int, int], channels: set[str]) -> bool:
    """True when ``path`` is an EXR that opens, decodes, and holds ``channels`` of ``shape`` (H, W)."""
    from svelive.exr import read_exr

    if not path.is_file():
        return False
    try:
        data, _ = read_exr(path)
    except SveliveError:
        return False
    return set(data) == channels and all(a.shape == shape for a in data.values())


def complete_frames(job: Job, indices: Iterable[int]) -> list[int]:
    """The frames among ``indices`` whose EXR is complete already (a task of its own)."""
    camera, reader = job_camera(job)
    with reader:
        shape = (reader.layout.height, reader.layout.width)
    channels = expected_channels(camera)
    return [i for i in indices if is_complete(frame_path(job.output, i), shape, channels)]


def staging_dir(job: Job, chunk: Chunk) -> Path:
    """Where a chunk that starts cold writes its EXRs until its start state is checked."""
    return Path(job.output) / ".svelive-pending" / f"{chunk.start:06d}-{chunk.stop:06d}"


#: Relative difference up to which two fused states count as the same (float32 rounding is 6e-8).
STATE_RTOL = 1e-6


def stream_state(reconstructor: Any, balancer: WhiteBalancer) -> dict[str, Any]:
    """Everything a stream carries from one frame to the next: the fused history's arrays
    (svelive.reconstruction.fusion.TemporalState), a colour stream's fused chroma, and the white
    balance's filter (multipliers, mode, time of its last measurement). The arrays are the
    stream's own (never modified after creation), not copies."""
    if not hasattr(reconstructor, "_history") or not hasattr(reconstructor, "_chroma"):
        raise SveliveError("svelive.reprocess: the Reconstructor no longer has the state this reads")
    state: dict[str, Any] = {}
    history = reconstructor._history  # the stream's state (no public accessor yet)
    if history is not None:
        state.update({name: value for name, value in vars(history).items() if isinstance(value, np.ndarray)})
    if reconstructor._chroma is not None:
        state["chroma"] = reconstructor._chroma
    current = balancer.current
    if current is not None:
        state["white_balance"] = (tuple(current.multipliers), current.mode, current.time_ns)
    return state


def compare_states(a: dict[str, Any] | None, b: dict[str, Any] | None, rtol: float = STATE_RTOL,
                   pixels: float = 0.0) -> tuple[bool, str | None]:
    """(same, what differs): two stream states are the same when they have the same parts, white
    balance mode and time (multipliers within ``rtol``) and, at all but a ``pixels`` fraction of
    the pixels (and of the chroma cells), the same history weight (so the same resets), the same
    boolean maps and every other number within ``rtol`` of the other relative to the larger, or to
    the plane's bright values (:func:`_beyond_rounding`).
    ``what differs`` is None when nothing does, else a few words (also when within ``pixels``)."""
    if a is None or b is None:
        return (a is b, None if a is b else "one stream has no state")
    if a.keys() != b.keys():
        return False, f"different state parts {sorted(a.keys() ^ b.keys())}"
    masks: dict[tuple[int, ...], np.ndarray] = {}  # differing positions by array shape (pixels, chroma cells)
    words = []
    for key in sorted(a):
        x, y = a[key], b[key]
        if key == "white_balance":
            (mx, *rx), (my, *ry) = x, y
            if rx != ry or not np.allclose(mx, my, rtol=rtol, atol=0):
                return False, f"white balance {x} != {y}"
            continue
        if x.shape != y.shape or x.dtype != y.dtype:
            return False, f"{key}: shape or type differs"
        if x.dtype == bool or key == "weight":
            bad = x != y
        else:
            bad = _beyond_rounding(x, y, rtol)
        count = int(np.count_nonzero(bad))
        if count:
            words.append(f"{key}: {count} values differ" + ("" if x.dtype == bool or key == "weight"
                                                            else f" by more than {rtol:g}"))
            where = bad.reshape(-1, *x.shape[-2:]).any(axis=0)
            masks[where.shape] = masks[where.shape] | where if where.shape in masks else where
    if not words:
        return True, None
    spread = {shape: int(np.count_nonzero(m)) for shape, m in masks.items()}
    same = all(n <= pixels * m.size for n, m in zip(spread.values(), masks.values()))
    total = sum(m.size for m in masks.values())
    return same, f"{'; '.join(words)} ({sum(spread.values())} of {total} positions)"


def _beyond_rounding(x: np.ndarray, y: np.ndarray, rtol: float) -> np.ndarray:
    """bool, x's shape: where x and y (float arrays (..., H, W)) differ by more than ``rtol`` times the
    larger of the two, or of the 99th percentile of |x| in their plane (H, W). A float32 running mean
    rounds relative to the readings that enter it, which near a mean of 0 are larger than the mean
    (a dark pixel's own readings through a short exposure): measured, 1 ulp of the plane's bright
    values where the mean is 5 DN."""
    x64, y64 = x.astype(np.float64), y.astype(np.float64)
    planes = np.abs(x64).reshape(-1, *x.shape[-2:])
    scale = np.array([np.percentile(p[np.isfinite(p)], 99) if np.isfinite(p).any() else 0.0 for p in planes])
    scale = scale.reshape(*x.shape[:-2], 1, 1) if x.ndim > 2 else scale[0]
    with np.errstate(invalid="ignore", over="ignore"):
        allowed = rtol * np.maximum(np.maximum(np.abs(x64), np.abs(y64)), scale)
        return ~((x64 == y64) | (np.abs(x64 - y64) <= allowed))


def compare_results(before: ChunkResult, after: ChunkResult, rtol: float = STATE_RTOL,
                    pixels: float = 0.0) -> tuple[bool, str | None]:
    """:func:`compare_states` of the state ``before`` ends with and the state ``after`` starts with."""
    return compare_states(before.end_state, after.start_state, rtol, pixels)


def stream_balance(result: Any, balancer: WhiteBalancer, time_ns: int) -> WhiteBalance | None:
    """The white balance of a stream's frame (a SequenceResult taken at ``time_ns``): ``balancer`` updated
    with its pixels that are not lower bounds; None for monochrome. Every frame goes through it, written or
    not (a warm-up's frames too), as the filter smooths over them all."""
    if result.image.ndim != 3:
        return None
    return balancer.update(result.image, time_ns, ~result.lower_bound)


def write_result(path: str | Path, result: Any, camera: Camera, colour: ColourSettings, balance: WhiteBalance | None,
                 *, frame_id: int, timestamp: float, attributes: dict[str, Any], half: bool) -> Path:
    """Write a stream's frame (a SequenceResult) with svelive.frame_exr: the image, ``confidence`` and
    ``motion``; ``movingFraction``, then ``attributes``, then the colour attributes."""
    info = FrameInfo(camera, result.method, frame_id=frame_id, timestamp=timestamp,
                     attributes={"movingFraction": f"{result.moving_fraction:.6f}", **attributes})
    planes = {"confidence": result.confidence, "motion": result.motion.astype(np.float32)}
    return write_frame_exr(path, result.image, info, colour, balance, planes, half=half)


def run_chunk(job: Job, chunk: Chunk, on_frame: Callable[[int], None] | None = None,
              stage: bool = False) -> ChunkResult:
    """Reconstruct frames ``chunk.first`` .. ``chunk.stop - 1`` in order and write the EXRs of
    ``chunk.start`` .. ``chunk.stop - 1`` that are not complete yet (into :func:`staging_dir`
    with ``stage``). A damaged frame is skipped (the stream goes on without it, as the replay
    source does). ``on_frame(index)`` is called after each written or skipped frame."""
    import dataclasses

    from replay import CorruptFrameError
    from svelive.memory import keep_freed_memory
    from svelive.reconstruction.stream import Reconstructor

    keep_freed_memory()  # in this worker process: frame buffers reused from frame to frame
    t0 = time.perf_counter()
    camera, reader = job_camera(job)
    output = staging_dir(job, chunk) if stage else Path(job.output)
    output.mkdir(parents=True, exist_ok=True)
    shape = (reader.layout.height, reader.layout.width)
    channels = expected_channels(camera)
    times = reader.timeline_ns()
    written, complete, damaged = [], [], []
    reconstructed = 0
    balancer = WhiteBalancer(job.colour)
    keeps_state = stateful(job, camera)
    final = Path(job.output)
    done = {i for i in range(chunk.start, chunk.stop) if is_complete(frame_path(final, i), shape, channels)}
    start_state = None
    noise_attributes = {} if job.noise is None else job.noise.attributes()
    with reader, Reconstructor(camera, method=job.method, temporal=job.temporal, exposure_timing=job.timing,
                               motion_config=job.motion) as reconstructor:
        # a chunk whose frames are all complete needs no warm-up: nothing to write
        first = chunk.first if len(done) < chunk.stop - chunk.start or chunk.start == chunk.stop else chunk.start
        for i in range(first, chunk.stop):
            if i == chunk.start and keeps_state:
                start_state = stream_state(reconstructor, balancer)
            if i in done:
                complete.append(i)
                if on_frame is not None:
                    on_frame(i)
                if not keeps_state:
                    continue
            try:
                frame = dataclasses.replace(reader.read(i), camera=camera)
            except CorruptFrameError:
                if i >= chunk.start:
                    damaged.append(i)
                    if on_frame is not None:
                        on_frame(i)
                continue
            result = reconstructor.process(frame)
            reconstructed += 1
            balance = stream_balance(result, balancer, int(times[i]))
            if i < chunk.start or i in done:
                continue
            write_result(frame_path(output, i), result, camera, job.colour, balance, frame_id=frame.frame_id,
                         timestamp=frame.host_time_ns / 1e9, attributes={"frameIndex": i, **noise_attributes},
                         half=job.half)
            written.append(i)
            if on_frame is not None:
                on_frame(i)
        if keeps_state and start_state is None:  # an empty chunk: the state before ``start``
            start_state = stream_state(reconstructor, balancer)
        end_state = stream_state(reconstructor, balancer) if keeps_state else None
    return ChunkResult(tuple(written), tuple(complete), tuple(damaged), reconstructed, time.perf_counter() - t0,
                       start_state, end_state, stage)


def commit_staged(job: Job, chunk: Chunk, frames: Iterable[int]) -> None:
    """Move a checked chunk's staged EXRs into the output (a rename each: atomic)."""
    import os

    staged = staging_dir(job, chunk)
    for i in frames:
        os.replace(frame_path(staged, i), frame_path(job.output, i))
    _remove_staging(job, chunk)


def _remove_staging(job: Job, chunk: Chunk) -> None:
    import shutil

    staged = staging_dir(job, chunk)
    shutil.rmtree(staged, ignore_errors=True)
    try:
        staged.parent.rmdir()  # the last chunk's takes the folder with it
    except OSError:
        pass


# ----- the client ------------------------------------------------------------------------------
@dataclass(frozen=True)
class Summary:
    """The outcome of a run: frames written, skipped as complete, damaged; frames reconstructed
    (warm-ups and re-runs included); wall seconds; chunk tasks run (re-runs included); chunks
    re-run because their warm-up had not converged; workers (0: in this process)."""

    written: int
    complete: int
    damaged: tuple[int, ...]
    reconstructed: int
    seconds: float
    chunks: int
    reruns: int
    workers: int
    reasons: tuple[str, ...] = ()
    tolerated: tuple[str, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        return {"written": self.written, "complete": self.complete, "damaged": list(self.damaged),
                "reconstructed": self.reconstructed, "seconds": round(self.seconds, 3), "chunks": self.chunks,
                "reruns": self.reruns, "rerun_reasons": list(self.reasons),
                "tolerated_differences": list(self.tolerated), "workers": self.workers,
                "fps": round(self.written / self.seconds, 3) if self.seconds > 0 else None}


def make_plan(job: Job, workers: int, complete: Iterable[int] = (), warmup: int | None = None,
              per_frame: bool = True) -> Plan:
    """The chunks that write every frame of ``job`` not in ``complete`` over ``workers`` workers;
    ``warmup`` overrides the fusion warm-up (frames); ``per_frame``: see :func:`plan`."""
    camera, reader = job_camera(job)
    with reader:
        n = len(reader) if job.frames is None else min(job.frames, len(reader))
        times = reader.timeline_ns()[:n]
    if n == 0:
        raise SveliveError(f"{job.recording}: the recording has no frames")
    done = set(complete)
    k = 0
    if job.temporal:
        k = fusion_warmup(job.motion) if warmup is None else int(warmup)
        if k < 0:
            raise SveliveError(f"--warmup must be >= 0 frames, got {warmup}")
    balancer = None
    span = 0.0
    if camera.cfa is not None and job.colour.auto:
        balancer = WhiteBalancer(job.colour)
        span = balancer.adapt_s * FLOAT32_BITS * math.log(2)
    chunks = plan([i for i in range(n) if i not in done], n, warmup=k, workers=max(1, workers), times_ns=times,
                  balancer=balancer, colour_warmup_s=span, per_frame=per_frame)
    return Plan(tuple(chunks), n, tuple(sorted(done & set(range(n)))), k, span)


def frame_count(job: Job) -> int:
    """Frames of the recording the job covers."""
    _, reader = job_camera(job)
    with reader:
        return len(reader) if job.frames is None else min(job.frames, len(reader))


def existing_outputs(job: Job, n: int) -> list[int]:
    """Frames among the first ``n`` that have a file at their EXR's path (complete or not)."""
    return [i for i in range(n) if frame_path(job.output, i).exists()]


class LocalBackend:
    """Runs chunks one after the other in this process; a state reference is the full ChunkResult."""

    def run(self, tasks: list[tuple[Job, Chunk, bool]]) -> Iterable[tuple[int, ChunkResult, Any]]:
        for k, (job, chunk, stage) in enumerate(tasks):
            result = run_chunk(job, chunk, stage=stage)
            yield k, result.without_states(), result

    def compare(self, before: Any, after: Any, pixels: float = 0.0) -> tuple[bool, str | None]:
        return compare_results(before, after, STATE_RTOL, pixels)


class DaskBackend:
    """Runs chunks as tasks of a dask.distributed Client. A state reference is the future of the
    full ChunkResult, which stays on its worker: states are compared on a worker (Dask moves one
    of them between workers), only small results come to the client."""

    def __init__(self, client: Any) -> None:
        self.client = client

    def run(self, tasks: list[tuple[Job, Chunk, bool]]) -> Iterable[tuple[int, ChunkResult, Any]]:
        from distributed import as_completed

        full = [self.client.submit(run_chunk, job, chunk, None, stage, pure=False) for job, chunk, stage in tasks]
        small = {self.client.submit(ChunkResult.without_states, f, pure=False): k for k, f in enumerate(full)}
        for future in as_completed(small):
            k = small[future]
            yield k, future.result(), full[k]

    def compare(self, before: Any, after: Any, pixels: float = 0.0) -> tuple[bool, str | None]:
        return self.client.submit(compare_results, before, after, STATE_RTOL, pixels, pure=False).result()


@dataclass(frozen=True)
class Outcome:
    """What :func:`execute` did: the results whose EXRs are in the output, frames reconstructed by
    every task (warm-ups, re-runs and reference runs included), tasks run, chunks re-run, and
    why each re-run was needed."""

    results: tuple[ChunkResult, ...]
    reconstructed: int
    tasks: int
    reruns: int
    reasons: tuple[str, ...] = ()
    tolerated: tuple[str, ...] = ()


def execute(job: Job, chunks: Iterable[Chunk], backend: Any, progress: Any = None, verify: bool = True,
            tolerance: float = 0.0) -> Outcome:
    """Run ``chunks`` on ``backend`` (LocalBackend, DaskBackend) and make the result the sequential run's.

    A chunk of a stream with state (:func:`stateful`) that starts cold (``first > 0``) writes into
    its staging folder; its state before ``start`` must be the same (:func:`compare_states`: the
    same resets, fused values within STATE_RTOL) as the state the run before it ends with: the
    previous chunk's end state when that chunk ends at ``start`` and was accepted itself (or
    starts at frame 0), else the state of a reference run warmed up twice as long. An accepted
    chunk's EXRs are moved into the output; another is run again with twice the warm-up (at most
    back to frame 0, which is the sequential run). ``tolerance``: the fraction of the pixels whose
    state may differ (a different reset, a value beyond STATE_RTOL) in an accepted chunk; the
    differences accepted so are listed (``Outcome.tolerated``). ``verify=False`` accepts every
    chunk as it comes (no staging).
    """
    pending = list(chunks)
    camera, reader = job_camera(job)
    with reader:
        times = reader.timeline_ns()
    keeps_state = stateful(job, camera) and verify
    measured = None
    if camera.cfa is not None and job.colour.auto:
        measured, _ = white_balance_chain(times, WhiteBalancer(job.colour))

    def longer(chunk: Chunk) -> Chunk:
        """The chunk with twice its warm-up (8 frames at least), started where the white balance measures."""
        first = max(0, chunk.start - max(2 * chunk.warmup, 8))
        while measured is not None and first > 0 and not measured[first]:
            first -= 1
        return Chunk(first, chunk.start, chunk.stop)

    final: dict[int, ChunkResult] = {}  # by chunk start: results whose EXRs are in the output
    waiting: dict[int, tuple[Chunk, ChunkResult, Any]] = {}  # staged, not yet checked
    ends: dict[int, Any] = {}  # by frame: the reference to the accepted state before it
    reconstructed = tasks = 0
    reasons: list[str] = []
    tolerated: list[str] = []
    while pending:
        batch = [(job, c, keeps_state and c.first > 0) for c in pending]
        tasks += len(batch)
        for k, result, ref in backend.run(batch):
            chunk = pending[k]
            reconstructed += result.reconstructed
            if result.staged:
                waiting[chunk.start] = (chunk, result, ref)
                continue
            final[chunk.start] = result
            if keeps_state:
                ends[chunk.stop] = ref
            if progress is not None:
                progress.update(len(result.written) + len(result.damaged))
        pending = []
        stops = {c.stop for c, _, _ in waiting.values()}
        alone = [c for start, (c, _, _) in sorted(waiting.items()) if start not in ends and start not in stops]
        if alone:  # cold chunks with nothing run before them: a reference run warmed up longer
            refs = [longer(Chunk(c.first, c.start, c.start)) for c in alone]
            tasks += len(refs)
            for k, result, ref in backend.run([(job, r, False) for r in refs]):
                reconstructed += result.reconstructed
                ends[alone[k].start] = _StartOf(ref)
        changed = True
        while changed:  # an accepted chunk makes the next one checkable
            changed = False
            for start, (chunk, result, ref) in sorted(waiting.items()):
                if start not in ends:
                    continue
                del waiting[start]
                changed = True
                before = ends[start]
                if isinstance(before, _StartOf):  # a reference run's start state against this one's
                    before = _as_end(before.ref, backend)
                same, reason = backend.compare(before, ref, tolerance)
                where = f"frames {chunk.start}-{chunk.stop - 1} after {chunk.warmup} frames of warm-up: {reason}"
                if same:
                    if reason is not None:
                        tolerated.append(where)
                    commit_staged(job, chunk, result.written)
                    final[start] = result
                    ends.pop(start)
                    ends[chunk.stop] = ref
                    if progress is not None:
                        progress.update(len(result.written) + len(result.damaged))
                else:
                    _remove_staging(job, chunk)
                    pending.append(longer(chunk))
                    reasons.append(where)
        if not pending and waiting:  # pragma: no cover - every waiting chunk has a predecessor or a reference
            raise SveliveError("svelive.reprocess: chunks left unchecked")
    return Outcome(tuple(r for _, r in sorted(final.items())), reconstructed, tasks, len(reasons), tuple(reasons),
                   tuple(tolerated))


@dataclass(frozen=True)
class _StartOf:
    """A reference run's result, whose start state (not its end state) is the one to compare with."""

    ref: Any


def _end_from_start(result: ChunkResult) -> ChunkResult:
    """A result whose end state is ``result``'s start state (for :func:`compare_results`)."""
    return replace(result, end_state=result.start_state)


def _as_end(ref: Any, backend: Any) -> Any:
    """A reference run's state reference turned so that :meth:`compare` reads its start state."""
    if isinstance(backend, DaskBackend):
        return backend.client.submit(_end_from_start, ref, pure=False)
    return _end_from_start(ref)


def run_local(job: Job, progress: Any = None, warmup: int | None = None, tolerance: float = 0.0) -> Summary:
    """Reprocess in this process, in frame order: from frame 0 when nothing is written yet (the
    sequential result); a resumed run starts its missing runs ``warmup`` frames early, checked
    as a worker's chunk is (:func:`execute`). A camera without gain or read noise gets the model of
    the recording's first frames (:func:`with_stream_noise`)."""
    t0 = time.perf_counter()
    job = with_stream_noise(job)
    n = frame_count(job)
    complete = complete_frames(job, existing_outputs(job, n))
    work = make_plan(job, 1, complete, warmup, per_frame=False)
    if progress is not None:
        progress.total = n
        if complete:
            progress.update(len(complete), skipped=True)

    return _summary(execute(job, work.chunks, LocalBackend(), progress, tolerance=tolerance), len(complete),
                    time.perf_counter() - t0, 0)


def _summary(outcome: Outcome, complete: int, seconds: float, workers: int) -> Summary:
    results = outcome.results
    return Summary(sum(len(r.written) for r in results), complete + sum(len(r.complete) for r in results),
                   tuple(sorted(i for r in results for i in r.damaged)), outcome.reconstructed, seconds,
                   outcome.tasks, outcome.reruns, workers, outcome.reasons, outcome.tolerated)


def require_dask() -> None:
    """A one-line SveliveError naming the pip extra when Dask's ``distributed`` cannot be imported (checked
    before any work)."""
    try:
        import distributed  # noqa: F401
    except ImportError:
        raise SveliveError(f"--workers/--scheduler need Dask: {INSTALL}") from None


def connect(workers: int, scheduler: str | None) -> Any:
    """A dask.distributed Client: to ``scheduler`` (``tcp://HOST:8786``), or to a new local cluster of
    ``workers`` processes with one thread each. A one-line error when Dask is not installed."""
    require_dask()
    from distributed import Client, LocalCluster

    if scheduler:
        try:
            return Client(scheduler, timeout="10s")
        except (OSError, TimeoutError) as exc:
            raise SveliveError(f"cannot reach the Dask scheduler {scheduler} ({exc}); start one with "
                               "`dask scheduler` and workers with `dask worker tcp://HOST:8786`") from None
    # the scheduler serves HTTP even without a dashboard, on 8787 unless told: a free port, so that a second
    # cluster on the machine (another run, a notebook) does not make it warn that 8787 is taken
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0")
    return Client(cluster)


def run_dask(job: Job, client: Any, workers: int, progress: Any = None, warmup: int | None = None,
             verify: bool = True, tolerance: float = 0.0) -> Summary:
    """Reprocess on the Dask cluster of ``client``: a check of the existing outputs, then the chunks of
    :func:`make_plan` as tasks (the workers read the recording and write the EXRs themselves),
    checked by :func:`execute` (``verify=False``: accepted as they are). A camera without gain or read
    noise gets the model of the recording's first frames (:func:`with_stream_noise`), estimated here."""
    t0 = time.perf_counter()
    job = with_stream_noise(job)
    n = frame_count(job)
    existing = existing_outputs(job, n)
    batches = [existing[k:k + 64] for k in range(0, len(existing), 64)]
    complete = [i for part in client.gather(client.map(complete_frames, [job] * len(batches), batches, pure=False))
                for i in part]
    work = make_plan(job, workers, complete, warmup)
    if progress is not None:
        progress.total = n
        if complete:
            progress.update(len(complete), skipped=True)

    return _summary(execute(job, work.chunks, DaskBackend(client), progress, verify, tolerance), len(complete),
                    time.perf_counter() - t0, workers)


# ----- any other stream (a camera, a folder of frames): in order, in this process ----------------
#: Frame time of frames without a timestamp (plain .npy directories): 30 fps, for the white balance's smoothing.
FRAME_NS = 33_333_333


def frame_time_ns(frame: Frame | np.ndarray, index: int) -> int:
    """A frame's time for the white balance's smoothing: the device's clock, else the arrival, else 30 fps
    (``index``: a bare raw array's position in its stream)."""
    if isinstance(frame, Frame):
        return frame.device_time_ns if frame.device_time_ns is not None else frame.host_time_ns
    return index * FRAME_NS


def run_stream(frames: Iterable[tuple[Frame | np.ndarray, Camera, NoiseEstimate]], output: str | Path, *,
               method: str | None = None, temporal: bool = True, timing: str = "mask",
               colour: ColourSettings | None = None, half: bool = False, limit: int | None = None,
               on_frame: Callable[[int], None] | None = None,
               on_camera: Callable[[NoiseEstimate], None] | None = None) -> int:
    """Reconstruct a stream in order and write ``frame_NNNNNN.exr`` for each frame (NNNNNN: its position in
    the stream) as a recording's chunk writes them (:func:`write_result`); returns the frames written.

    Args:
        frames: (a Frame or a bare raw array, the camera to reconstruct it with, its noise model), in order
            (svelive.cli.motion.with_cameras); a frame whose camera differs from the one before it
            starts a new stream, and ``on_camera`` is given its noise model.
        output: the output directory, made at the first frame.
        method, temporal, timing, colour, half: as in :class:`Job`.
        limit: stop after this many frames (None: at the stream's end).
        on_frame: called with the count written after each frame.
    """
    from svelive.reconstruction.stream import Reconstructor

    colour = colour or ColourSettings()
    balancer = WhiteBalancer(colour)
    reconstructor: Reconstructor | None = None
    n = 0
    try:
        for frame, camera, noise in frames:
            if reconstructor is None or camera != reconstructor.camera:
                if on_camera is not None:
                    on_camera(noise)
                if reconstructor is not None:
                    reconstructor.close()
                reconstructor = Reconstructor(camera, method=method, temporal=temporal, exposure_timing=timing)
            result = reconstructor.process(getattr(frame, "raw", frame))
            time_ns = frame_time_ns(frame, n)
            balance = stream_balance(result, balancer, time_ns)
            Path(output).mkdir(parents=True, exist_ok=True)
            write_result(frame_path(output, n), result, camera, colour, balance,
                         frame_id=getattr(frame, "frame_id", n), timestamp=time_ns / 1e9,
                         attributes=noise.attributes(), half=half)
            n += 1
            if on_frame is not None:
                on_frame(n)
            if limit is not None and n >= limit:
                break
    finally:
        if reconstructor is not None:
            reconstructor.close()
    return n
