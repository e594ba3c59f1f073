"""Kernels compiled in a child process (svelive.jit.compile_elsewhere): the process that asked then loads them
from numba's disk cache and compiles nothing, so it never holds the compiler's memory (the live service's
start, service.commands.warm_up_kernels); where no child can compile, the service compiles itself and says so."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

TINY = '''
import time

import numpy as np

from svelive.jit import kernel


@kernel
def double(x):
    for i in range(x.size):
        x[i] *= 2


@kernel
def triple(x):
    for i in range(x.size):
        x[i] *= 3


def warm():
    double(np.ones(3, np.float32))


def fail():
    raise SystemExit(3)


def forever():
    time.sleep(600)
'''

PARENT = '''
import json
import sys

import numpy as np
from numba.core import event

import tiny
from svelive.jit import compile_elsewhere

compiled = {}
with event.install_recorder("numba:compile") as recorder:
    why = compile_elsewhere(tiny.warm)
    tiny.warm()
    compiled["double"] = sum(1 for _, e in recorder.buffer if e.is_start)
with event.install_recorder("numba:compile") as recorder:  # a kernel no child ran: compiled here
    tiny.triple(np.ones(3, np.float32))
    compiled["triple"] = sum(1 for _, e in recorder.buffer if e.is_start)
failed = compile_elsewhere(tiny.fail)
print(json.dumps({"why": why, "compiled": compiled, "loaded": sum(tiny.double.stats.cache_hits.values()),
                  "failed": failed}))
'''


def test_a_child_compiles_and_the_parent_only_loads(tmp_path):
    (tmp_path / "tiny.py").write_text(TINY)
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache"),
           "PYTHONPATH": os.pathsep.join([str(tmp_path), str(ROOT)])}
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(PARENT)], env=env, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    said = json.loads(out.stdout.splitlines()[-1])
    assert said["why"] is None
    assert said["compiled"] == {"double": 0, "triple": 1}  # the recorder sees what this process compiles
    assert said["loaded"] == 1  # double's one signature, from the cache the child filled
    assert said["failed"] == "the compiling process failed (exit code 3)"


def test_the_compiling_child_stops_when_its_parent_has_gone(tmp_path):
    """A child whose parent is not the one it was started by (pid 0: none) exits at once, not after its warm-up."""
    (tmp_path / "tiny.py").write_text(TINY)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(ROOT)])}
    code = "from svelive.jit import _compile_child; _compile_child('tiny', 'forever', 0)"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=60)
    assert out.returncode == 1, out.stderr


def test_the_service_compiles_itself_and_says_so_where_no_child_can(monkeypatch, capsys):
    import svelive.jit

    from service import commands

    ran = []
    monkeypatch.setattr(svelive.jit, "compile_elsewhere", lambda warm: "no process to compile in (test)")
    monkeypatch.setattr(commands, "compile_service_kernels", lambda: ran.append(True))
    commands.warm_up_kernels("svelive serve")
    assert ran == [True]
    err = capsys.readouterr().err
    assert "svelive serve: no process to compile in (test): compiling the kernels in this process" in err, err
