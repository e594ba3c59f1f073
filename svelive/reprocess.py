"""Reprocessing a recording: frames to EXR files, in this process or on a Dask cluster.

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
  exact from then on. The history cannot be reset on demand without changing the
  output, so this is not bit-exact in general: a few pixels whose test statistic sits
  within rounding of the threshold can decide differently (tests/test_reprocess.py
  measures it).
- The automatic white balance of a colour recording is a first-order low-pass
  filter over frame time (svelive.whitebalance.WhiteBalancer, time constant
  ``adapt_s``), measured on every frame ``measure_s`` after the previous
  measurement: a colour chunk starts at a frame that the sequential run measures
  too (the measurement times follow from the timestamps alone) and at least
  ``adapt_s * 24 ln 2`` seconds of frame time (16.6 s) before ``start``, or at a
  gap longer than ``reset_after_s``, where the filter restarts exactly.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from svelive.camera import Camera
from svelive.errors import SveliveError
from svelive.reconstruction.config import MotionConfig
from svelive.whitebalance import ColourSettings, WhiteBalancer

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
    frames reconstructed (warm-up included) in ``seconds`` of wall time."""

    written: tuple[int, ...]
    complete: tuple[int, ...]
    damaged: tuple[int, ...]
    reconstructed: int
    seconds: float


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
        sensor = camera.sensor
        camera = camera.replace(sensor=replace(sensor, gain=job.gain if job.gain is not None else sensor.gain,
                                               read_noise=job.read_noise if job.read_noise is not None
                                               else sensor.read_noise))
    return camera, RecordingReader(job.recording, warn=False)


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


def run_chunk(job: Job, chunk: Chunk, on_frame: Callable[[int], None] | None = None) -> ChunkResult:
    """Reconstruct frames ``chunk.first`` .. ``chunk.stop - 1`` in order and write the EXRs of
    ``chunk.start`` .. ``chunk.stop - 1`` that are not complete yet. A damaged frame is skipped
    (the stream goes on without it, as the replay source's reader does). ``on_frame(index)``
    is called after each written or skipped frame of the chunk."""
    import dataclasses

    from replay import CorruptFrameError
    from svelive.exr import write_exr
    from svelive.reconstruction.stream import Reconstructor
    from svelive.whitebalance import exr_output

    t0 = time.perf_counter()
    camera, reader = job_camera(job)
    output = Path(job.output)
    output.mkdir(parents=True, exist_ok=True)
    shape = (reader.layout.height, reader.layout.width)
    channels = expected_channels(camera)
    times = reader.timeline_ns()
    written, complete, damaged = [], [], []
    reconstructed = 0
    balancer = WhiteBalancer(job.colour)
    # a chunk whose frames are all complete needs no warm-up: nothing to write
    todo = [i for i in range(chunk.start, chunk.stop)
            if not is_complete(frame_path(output, i), shape, channels)]
    done = set(range(chunk.start, chunk.stop)) - set(todo)
    last = max(todo) + 1 if todo else chunk.start
    with reader, Reconstructor(camera, method=job.method, temporal=job.temporal, exposure_timing=job.timing,
                               motion_config=job.motion) as reconstructor:
        for i in range(chunk.first if todo else chunk.start, chunk.stop):
            if i in done:
                complete.append(i)
                if on_frame is not None:
                    on_frame(i)
                if not job.temporal and camera.cfa is None:
                    continue
            if i >= last:
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
            balance = None
            if result.image.ndim == 3:
                balance = balancer.update(result.image, int(times[i]), ~result.lower_bound)
            if i < chunk.start or i in done:
                continue
            data, colour = exr_output(result.image, balance, job.colour)
            attributes = {"svelive_method": result.method, "svelive_pattern": str(camera.pattern),
                          "svelive_moving_fraction": f"{result.moving_fraction:.6f}",
                          "svelive_frame_index": i, "svelive_frame_id": frame.frame_id, **colour}
            if camera.cfa is not None:
                attributes["cfa"] = camera.cfa.name
            write_exr(frame_path(output, i),
                      {**data, "confidence": result.confidence, "motion": result.motion.astype(np.float32)},
                      attributes, half=job.half)
            written.append(i)
            if on_frame is not None:
                on_frame(i)
    return ChunkResult(tuple(written), tuple(complete), tuple(damaged), reconstructed, time.perf_counter() - t0)


# ----- the client ------------------------------------------------------------------------------
@dataclass(frozen=True)
class Summary:
    """The outcome of a run: frames written, skipped as complete, damaged; frames reconstructed
    (warm-ups included); wall seconds; chunks; workers (0: in this process)."""

    written: int
    complete: int
    damaged: tuple[int, ...]
    reconstructed: int
    seconds: float
    chunks: int
    workers: int

    def to_dict(self) -> dict[str, Any]:
        return {"written": self.written, "complete": self.complete, "damaged": list(self.damaged),
                "reconstructed": self.reconstructed, "seconds": round(self.seconds, 3), "chunks": self.chunks,
                "workers": self.workers,
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


def run_local(job: Job, progress: Any = None, warmup: int | None = None) -> Summary:
    """Reprocess in this process, in frame order: from frame 0 when nothing is written yet (the
    sequential result); a resumed run starts its missing runs ``warmup`` frames early, as a worker would."""
    t0 = time.perf_counter()
    n = frame_count(job)
    complete = complete_frames(job, existing_outputs(job, n))
    work = make_plan(job, 1, complete, warmup, per_frame=False)
    if progress is not None:
        progress.total = n
        if complete:
            progress.update(len(complete), skipped=True)
    results = [run_chunk(job, chunk, on_frame=None if progress is None else (lambda i: progress.update()))
               for chunk in work.chunks]
    return _summary(results, len(complete), time.perf_counter() - t0, len(work.chunks), 0)


def _summary(results: list[ChunkResult], complete: int, seconds: float, chunks: int, workers: int) -> Summary:
    return Summary(sum(len(r.written) for r in results), complete + sum(len(r.complete) for r in results),
                   tuple(sorted(i for r in results for i in r.damaged)), sum(r.reconstructed for r in results),
                   seconds, chunks, workers)


def connect(workers: int, scheduler: str | None) -> Any:
    """A dask.distributed Client: to ``scheduler`` (``tcp://HOST:8786``), or to a new local cluster of
    ``workers`` processes with one thread each. A one-line error when Dask is not installed."""
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise SveliveError(f"--workers/--scheduler need Dask: {INSTALL}") from None
    if scheduler:
        try:
            return Client(scheduler, timeout="10s")
        except (OSError, TimeoutError) as exc:
            raise SveliveError(f"cannot reach the Dask scheduler {scheduler} ({exc}); start one with "
                               "`dask scheduler` and workers with `dask worker tcp://HOST:8786`") from None
    cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None)
    return Client(cluster)


def run_dask(job: Job, client: Any, workers: int, progress: Any = None, warmup: int | None = None) -> Summary:
    """Reprocess on the Dask cluster of ``client``: a check of the existing outputs, then the chunks of
    :func:`make_plan` as tasks (the workers read the recording and write the EXRs themselves)."""
    from distributed import as_completed

    t0 = time.perf_counter()
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
    futures = [client.submit(run_chunk, job, chunk, pure=False) for chunk in work.chunks]
    results = []
    for future in as_completed(futures):
        result: ChunkResult = future.result()
        results.append(result)
        if progress is not None:
            progress.update(len(result.written) + len(result.damaged))
            if result.complete:
                progress.update(len(result.complete), skipped=True)
    return _summary(results, len(complete), time.perf_counter() - t0, len(work.chunks), workers)
