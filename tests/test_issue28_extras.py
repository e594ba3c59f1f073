"""Issue 28.3: README commands that need an extra. ``reconstruct-sequence --workers 2`` without Dask says so in
one line naming the pip extra before any work (before: after the recording was read and its noise estimated;
here, with a recording that does not exist, the missing file was said instead); ``bench`` announces each part
as it starts, with the time so far."""

from __future__ import annotations

import argparse
import subprocess
import sys
import time

from svelive.cli.bench import part_announcer

#: the interpreter of a machine without Dask: ``distributed`` cannot be imported
WITHOUT_DASK = "import sys; sys.modules['distributed'] = None; from svelive.cli import main; sys.exit(main())"


def test_reconstruct_sequence_on_dask_without_dask_names_the_extra_before_any_work(tmp_path):
    started = time.monotonic()
    out = subprocess.run([sys.executable, "-c", WITHOUT_DASK, "reconstruct-sequence", "--source",
                          f"replay:{tmp_path / 'absent.sverec'}", "-o", tmp_path / "exr", "--workers", "2"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and "need Dask" in lines[0] and 'svelive[cluster]' in lines[0], out.stderr
    assert not (tmp_path / "exr").exists() and time.monotonic() - started < 30


def test_bench_announces_each_part_with_the_time_so_far(capsys):
    args = argparse.Namespace(no_mono=False, no_live=True, no_colour=False, no_grid=True, no_stability=False)
    say = part_announcer(args, time.perf_counter())
    for name in ("mono", "colour", "stability"):
        say(name)
    lines = capsys.readouterr().err.splitlines()
    assert [line.split(" (")[0] for line in lines] == ["svelive bench: [1/3] mono", "svelive bench: [2/3] colour",
                                                       "svelive bench: [3/3] stability"]
    assert all(line.endswith("s so far)") for line in lines), lines
