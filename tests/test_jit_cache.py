"""The kernels' disk cache is valid for the whole package's sources: a kernel built into another kernel is
never loaded from a cache made before its source changed (a checkout updated in part)."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import svelive
from svelive.jit import _PackageStamp, package_digest
from svelive.reconstruction.colour.shares import _sorted3

CALLER = """from svelive.jit import kernel
from svelive._probe_callee import callee


@kernel
def caller(x):
    return callee(x) + 1.0
"""
CALLEE = """from svelive.jit import kernel


@kernel
def callee(x):
    return x * {factor}
"""


def test_the_digest_follows_every_source_file_and_only_sources(tmp_path):
    (tmp_path / "sub").mkdir()
    (tmp_path / "a.py").write_text("x = 1\n")
    (tmp_path / "sub" / "b.py").write_text("y = 2\n")
    first = package_digest(str(tmp_path))
    package_digest.cache_clear()
    (tmp_path / "notes.txt").write_text("not a source")
    assert package_digest(str(tmp_path)) == first
    package_digest.cache_clear()
    (tmp_path / "sub" / "b.py").write_text("y = 3\n")
    assert package_digest(str(tmp_path)) != first
    package_digest.cache_clear()


def test_a_kernel_cache_is_stamped_with_the_package():
    locator = _sorted3._cache._impl.locator
    assert isinstance(locator, _PackageStamp)
    own, package = locator.get_source_stamp()
    assert package == package_digest() and own


def _call(package_parent: Path, cache: Path) -> str:
    env = {**os.environ, "PYTHONPATH": str(package_parent), "NUMBA_CACHE_DIR": str(cache)}
    code = "from svelive._probe_caller import caller; print(caller(1.0))"
    # (run there: ``-c`` puts the working directory first on sys.path, which may hold another svelive)
    done = subprocess.run([sys.executable, "-c", code], env=env, cwd=package_parent, capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


def test_a_changed_callee_in_another_module_is_compiled_again(tmp_path):
    package = tmp_path / "svelive"
    shutil.copytree(Path(svelive.__file__).parent, package, ignore=shutil.ignore_patterns("__pycache__"))
    (package / "_probe_caller.py").write_text(CALLER)
    (package / "_probe_callee.py").write_text(CALLEE.format(factor=2.0))
    cache = tmp_path / "cache"
    assert _call(tmp_path, cache) == "3.0"
    assert _call(tmp_path, cache) == "3.0"  # (loaded from the cache)
    (package / "_probe_callee.py").write_text(CALLEE.format(factor=3.0))
    assert _call(tmp_path, cache) == "4.0"  # numba's own stamp, the caller's file alone, would load 3.0
