"""Reprocessing a recording (svelive.reprocess): on a local Dask cluster of 2 workers the EXRs equal
the sequential run's, a second run skips the complete ones and redoes a truncated one; the
progress counter; reconstruct-sequence's sensor levels for a recording."""

from __future__ import annotations

import dataclasses
import io
import sys
from pathlib import Path

import numpy as np
import pytest

from replay import RecordingReader
from svelive import reprocess
from svelive.cli import main
from svelive.exr import read_exr
from svelive.progress import Progress, format_progress
from svelive.reconstruction.config import MotionConfig
from svelive.reconstruction.stream import NOISE_FRAMES, Reconstructor, stream_noise

#: a short history so that a 60-frame recording splits into chunks with their full warm-up
MOTION = MotionConfig(max_history=2)


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("rec") / "demo.sverec"
    assert main(["record", "--source", "demo", "--cfa", "none", "--width", "64", "--height", "48", "--fps", "0",
                 "--frames", "60", "--black-level", "64", "-q", "-o", str(path)]) == 0
    return path


@pytest.fixture(scope="module")
def client():
    pytest.importorskip("distributed")
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster, \
            Client(cluster) as c:
        yield c


def estimated(camera, raws: list[np.ndarray]):
    """``camera`` with the noise model of the stream's first frames, as a job without gain or read noise
    reconstructs with (the demo camera gives neither)."""
    return camera.replace(sensor=stream_noise(raws[:NOISE_FRAMES], camera).apply(camera.sensor))


def sequential(path: Path, frames: int, **kwargs) -> list:
    """The reference: one Reconstructor over the recording's frames in order, with the noise model of its
    first frames."""
    with RecordingReader(path) as reader:
        raws = [reader.read(i).raw for i in range(frames)]
        camera = estimated(reader.camera, raws)
    with Reconstructor(camera, **kwargs) as reconstructor:
        return [reconstructor.process(raw) for raw in raws]


def exr(directory: Path, i: int) -> dict[str, np.ndarray]:
    return read_exr(reprocess.frame_path(directory, i))[0]


def assert_rounding_apart(got: np.ndarray, want: np.ndarray) -> None:
    """The criterion of reprocess.compare_states: within STATE_RTOL of the larger value or of the
    frame's bright values (99th percentile), the scale of a running mean's rounding."""
    scale = float(np.percentile(np.abs(want), 99))
    np.testing.assert_allclose(got, want, rtol=reprocess.STATE_RTOL, atol=reprocess.STATE_RTOL * scale)


def test_single_frame_method_on_dask_equals_the_sequential_run(recording: Path, client, tmp_path: Path) -> None:
    job = reprocess.Job(str(recording), str(tmp_path), temporal=False, frames=10)
    summary = reprocess.run_dask(job, client, 2)
    assert (summary.written, summary.chunks, summary.reconstructed) == (10, 10, 10)  # one task per frame
    for i, want in enumerate(sequential(recording, 10, temporal=False)):
        got = exr(tmp_path, i)
        np.testing.assert_array_equal(got["Y"], want.image)
        np.testing.assert_array_equal(got["confidence"], want.confidence)
    # the demo camera gives no gain or read noise: the model of the first three frames, named in every EXR
    with RecordingReader(recording) as reader:
        camera, raws = reader.camera, [reader.read(i).raw for i in range(NOISE_FRAMES)]
    model = stream_noise(raws, camera)
    for i in (0, 9):
        attributes = read_exr(reprocess.frame_path(tmp_path, i))[1]
        assert attributes["noiseSource"] == "estimated"
        assert attributes["noiseGain"] == pytest.approx(model.gain, rel=1e-6)
    assert not np.array_equal(exr(tmp_path, 0)["Y"], Reconstructor(camera, temporal=False).process(raws[0]).image)


def test_temporal_chunks_on_dask_equal_the_sequential_run(recording: Path, client, tmp_path: Path) -> None:
    want = sequential(recording, 60, motion_config=MOTION)
    k = reprocess.fusion_warmup(MOTION)
    assert k == 2 + 24  # the history's difference halves each frame: 24 halvings reach float32 rounding
    job = reprocess.Job(str(recording), str(tmp_path / "k"), motion=MOTION)
    plan = reprocess.make_plan(job, 2)
    assert [(c.first, c.start, c.stop) for c in plan.chunks] == [(0, 0, 30), (30 - k, 30, 60)]
    summary = reprocess.run_dask(job, client, 2)
    assert (summary.written, summary.reruns, summary.reconstructed) == (60, 0, 60 + k)
    fused = 0
    for i in range(60):
        got = exr(tmp_path / "k", i)
        np.testing.assert_array_equal(got["motion"], want[i].motion)
        assert_rounding_apart(got["Y"], want[i].image)
        fused += int(np.count_nonzero(want[i].weight < 1))
    assert fused > 0  # the frames were fused
    assert not (tmp_path / "k" / ".svelive-pending").exists()


def test_a_chunk_whose_warmup_was_too_short_is_run_again(recording: Path, client, tmp_path: Path) -> None:
    want = sequential(recording, 60, motion_config=MOTION)
    # unchecked, chunks started 2 frames early differ from the sequential run
    cold = reprocess.Job(str(recording), str(tmp_path / "cold"), motion=MOTION)
    assert reprocess.run_dask(cold, client, 2, warmup=2, verify=False).reruns == 0
    assert not np.array_equal(exr(tmp_path / "cold", 30)["Y"], want[30].image)
    # checked, the second chunk's state before frame 30 differs from the first's at its end: run again
    job = reprocess.Job(str(recording), str(tmp_path / "checked"), motion=MOTION)
    summary = reprocess.run_dask(job, client, 2, warmup=2)
    assert summary.written == 60 and summary.reruns >= 1 and "differ" in summary.reasons[0]
    for i in (29, 30, 31, 59):
        assert_rounding_apart(exr(tmp_path / "checked", i)["Y"], want[i].image)


def test_state_comparison_counts_other_resets_and_values_beyond_rounding() -> None:
    rng = np.random.default_rng(3)
    mean = rng.uniform(1, 100, (8, 10)).astype(np.float32)
    a = {"mean": mean, "weight": np.full((8, 10), 0.125, np.float32), "bound": np.zeros((8, 10), bool),
         "white_balance": ((1.5, 1.0, 2.0), "auto", 7)}
    b = {**a, "mean": mean * np.float32(1 + 2e-7)}  # a few float32 roundings apart
    assert reprocess.compare_states(a, b) == (True, None)
    weight = a["weight"].copy()
    weight[3, 4] = 1.0  # one pixel reset in one run only
    c = {**b, "weight": weight}
    same, why = reprocess.compare_states(a, c)
    assert not same and why == "weight: 1 values differ (1 of 80 positions)"
    assert reprocess.compare_states(a, c, pixels=1 / 80) == (True, why)  # within a tolerance of 1 pixel in 80
    d = {**a, "mean": mean * np.float32(1 + 1e-4)}
    assert reprocess.compare_states(a, d)[0] is False
    # near 0 a mean's rounding is that of the readings entering it: the plane's bright values set the scale
    dark = mean.copy()
    dark[0, 0] = 0.01
    darker = dark.copy()
    darker[0, 0] = 0.01 + 2e-5  # 2e-3 relative to itself, 2e-7 of the plane's bright values (~100)
    assert reprocess.compare_states({**a, "mean": dark}, {**a, "mean": darker}) == (True, None)
    e = {**a, "white_balance": ((1.5, 1.0, 2.0), "auto", 8)}  # measured at another time
    assert reprocess.compare_states(a, e)[0] is False


def test_resume_skips_complete_exrs_and_redoes_a_truncated_one(recording: Path, client, tmp_path: Path) -> None:
    job = reprocess.Job(str(recording), str(tmp_path), temporal=False, frames=6)
    assert reprocess.run_dask(job, client, 2).written == 6
    paths = [reprocess.frame_path(tmp_path, i) for i in range(6)]
    before = {p: p.stat().st_mtime_ns for p in paths}
    truncated = paths[3].read_bytes()
    paths[3].write_bytes(truncated[: len(truncated) // 2])
    summary = reprocess.run_dask(job, client, 2)
    assert (summary.written, summary.complete) == (1, 5)
    assert all(p.stat().st_mtime_ns == before[p] for p in paths if p != paths[3])
    assert paths[3].read_bytes() == truncated  # redone, the same
    assert not list(tmp_path.glob(".*.tmp"))  # no temporary file left behind


def test_a_resumed_temporal_run_warms_up_before_the_missing_frames(recording: Path, tmp_path: Path) -> None:
    job = reprocess.Job(str(recording), str(tmp_path), motion=MOTION, frames=40)
    assert reprocess.run_local(job).written == 40
    reprocess.frame_path(tmp_path, 35).unlink()
    plan = reprocess.make_plan(job, 1, [i for i in range(40) if i != 35])
    assert [(c.first, c.start, c.stop) for c in plan.chunks] == [(35 - 26, 35, 36)]
    summary = reprocess.run_local(job)
    # the chunk, a reference run warmed up twice as long (here from frame 0) to check its state against,
    # and the chunk again from frame 0 if they differed
    assert (summary.written, summary.complete) == (1, 39)
    assert summary.reconstructed == 27 + 35 + summary.reruns * 36
    want = sequential(recording, 36, motion_config=MOTION)[35]
    assert_rounding_apart(exr(tmp_path, 35)["Y"], want.image)


def test_workers_without_dask_is_a_one_line_error_naming_the_extra(recording: Path, tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed raises ImportError
    assert main(["reconstruct-sequence", "--source", f"replay:{recording}", "--workers", "2", "-q",
                 "-o", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and 'svelive[cluster]' in err and "dask[distributed]" in err


def test_recorded_and_given_black_level_for_a_recording(recording: Path, tmp_path: Path) -> None:
    with RecordingReader(recording) as reader:
        camera = reader.camera
        raw = reader.read(0)
    assert camera.sensor.black_level == 64
    assert main(["reconstruct-sequence", "--source", f"replay:{recording}", "--frames", "1", "--no-temporal", "-q",
                 "-o", str(tmp_path / "recorded")]) == 0
    np.testing.assert_array_equal(exr(tmp_path / "recorded", 0)["Y"],  # --frames 1: the model of one frame
                                  Reconstructor(estimated(camera, [raw.raw]), temporal=False).process(raw.raw).image)
    assert main(["reconstruct-sequence", "--source", f"replay:{recording}", "--frames", "1", "--no-temporal", "-q",
                 "--black-level", "16", "-o", str(tmp_path / "given")]) == 0
    other = camera.replace(sensor=dataclasses.replace(camera.sensor, black_level=16))
    got = exr(tmp_path / "given", 0)["Y"]
    np.testing.assert_array_equal(got, Reconstructor(estimated(other, [raw.raw]), temporal=False).process(raw.raw).image)
    assert np.median(got) > np.median(exr(tmp_path / "recorded", 0)["Y"])
    # the model is named in the EXR: one 64x48 frame has too few samples, so the defaults, said so
    attributes = read_exr(reprocess.frame_path(tmp_path / "recorded", 0))[1]
    assert (attributes["noiseSource"], attributes["noiseGain"]) == ("default", pytest.approx(camera.sensor.effective_gain))


def test_progress_counts_and_rate_and_quiet() -> None:
    now = [0.0]
    out = io.StringIO()
    progress = Progress("work", total=4, stream=out, clock=lambda: now[0], log_interval_s=1.0)
    for i in range(4):
        now[0] += 0.75
        progress.update(skipped=i == 0)
    progress.close()
    lines = out.getvalue().splitlines()
    assert lines[-1] == "work: 4/4 frames (100%), 1 skipped, 1 frames/s"  # 3 done in 3 s
    assert lines[0].startswith("work: 2/4 frames (50%)")  # a log line once 1 s passed, not every update
    quiet = io.StringIO()
    with Progress("work", stream=quiet, quiet=True) as p:
        p.update()
    assert quiet.getvalue() == ""
    assert format_progress("x", 5, 10, 10.0) == "x: 5/10 frames (50%), 0.5 frames/s, 10 s left"


def test_progress_leaves_the_last_line_to_an_error() -> None:
    out = io.StringIO()
    with pytest.raises(ValueError), Progress("work", total=3, stream=out, log_interval_s=0.0) as progress:
        progress.update()
        raise ValueError("bad")
    lines = out.getvalue().splitlines()
    assert len(lines) == 1 and lines[0].startswith("work: 1/3 frames (33%)")  # the update's line, no final one
