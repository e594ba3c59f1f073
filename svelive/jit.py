"""Compiled per-pixel kernels: the one way svelive compiles Python loops (numba).

The methods and the motion stage are chains of per-pixel arithmetic between a
few window sums. Done as numpy operations each link reads and writes whole
arrays, so a frame costs tens of passes over memory; a kernel fuses a chain
into one pass. Window sums stay with OpenCV (``methods.base.smooth``), which
vectorises them better than a loop would.

Rules for a kernel (what makes LLVM vectorise it, and keeps it thread-safe):
- decorate it with :data:`kernel`; it releases the GIL, so strips of one frame
  run in parallel on the caller's threads (no numba threading of its own,
  which would oversubscribe the two cores the service shares with OpenCV);
- loop over flat, C-contiguous float32 arrays (``flat``), write into outputs
  the caller allocates, and keep constants float32 (``np.float32(...)``): a
  float64 literal turns the whole chain into float64;
- no raising: the numpy error model gives inf/nan on division by zero, as numpy does.

The first call of a kernel compiles it (about a second); numba's disk cache keeps the
machine code (``__pycache__`` or ``$NUMBA_CACHE_DIR``), so later processes load it in
milliseconds. A kernel's cache entry holds for the sources of the whole package, not its own
file alone (:func:`kernel`): any change to a svelive source compiles every kernel again.
Compiling leaves the process holding LLVM's memory for good (the live service's monochrome server: about 130 MB more
resident after one source file's kernels compiled in it, about 500 MB after it
compiled every kernel), so a long-running process compiles in a child first
(:func:`compile_elsewhere`) and only loads.
"""

from __future__ import annotations

import functools
import hashlib
import importlib
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from functools import partial

import numba
import numpy as np
from numba import types
from numba.core import caching
from numba.extending import intrinsic

@functools.cache
def package_digest(root: str = os.path.dirname(os.path.abspath(__file__))) -> bytes:
    """SHA-256 of every ``.py`` file under ``root`` (svelive's package directory), their paths relative to it
    and their contents, in sorted order: what every kernel's cache entry is valid for (:func:`kernel`)."""
    digest = hashlib.sha256()
    for folder, dirs, files in sorted(os.walk(root)):
        dirs.sort()
        for name in sorted(files):
            if name.endswith(".py"):
                path = os.path.join(folder, name)
                digest.update(os.path.relpath(path, root).encode())
                with open(path, "rb") as source:
                    digest.update(hashlib.sha256(source.read()).digest())
    return digest.digest()


class _PackageStamp:
    """A numba cache locator's mixin: the source stamp of a kernel's cache index is its own file's and
    :func:`package_digest`'s. numba's own stamp covers only the file that defines the kernel, but a kernel
    compiles in the kernels it calls from other modules, so a checkout updated in part (``git pull``) would
    otherwise load a kernel built from the old code of the ones it calls."""

    def get_source_stamp(self) -> tuple:
        return super().get_source_stamp(), package_digest()


class _UserProvidedLocator(_PackageStamp, caching.UserProvidedCacheLocator):
    pass


class _InTreeLocator(_PackageStamp, caching.InTreeCacheLocator):
    pass


class _UserWideLocator(_PackageStamp, caching.UserWideCacheLocator):
    pass


class _KernelCacheImpl(caching.CompileResultCacheImpl):
    # (numba's own for a package imported from a zip, whose stamp is the whole archive's)
    _locator_classes = [_UserProvidedLocator, _InTreeLocator, _UserWideLocator, caching.IPythonCacheLocator,
                        caching.ZipCacheLocator]


class _KernelCache(caching.FunctionCache):
    _impl_class = _KernelCacheImpl


def kernel(function: Callable | None = None, **options) -> Callable:
    """Decorator of every compiled kernel (``@kernel`` or ``@kernel(inline="always")``, options of
    ``numba.njit``): no GIL, numpy's division semantics, and cached on disk (numba's ``cache=True``, with the
    index stamped by the whole package: :class:`_PackageStamp`)."""
    if function is None:
        return partial(kernel, **options)
    dispatcher = numba.njit(nogil=True, error_model="numpy", **options)(function)
    dispatcher._cache = _KernelCache(dispatcher.py_func)  # what numba's enable_caching does, with our locators
    return dispatcher


def compile_elsewhere(warm: Callable[[], None]) -> str | None:
    """Run ``warm`` (a module-level function that calls kernels) in a short-lived child process, which compiles
    into numba's disk cache what is not there yet, so that this process then loads the kernels instead of
    compiling them. None when the child finished; else why it did not (the caller may warm up here instead).

    The child is this interpreter on this ``sys.path`` and environment, so it reads the same sources and numba
    picks the same cache directory (the first writable one of ``$NUMBA_CACHE_DIR``, ``__pycache__``, the user's);
    it stops when this process goes (:func:`_compile_child`).
    """
    call = f"_compile_child({warm.__module__!r}, {warm.__qualname__!r}, {os.getpid()})"
    code = f"from svelive.jit import _compile_child; {call}"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(path for path in sys.path if path)}
    try:
        done = subprocess.run([sys.executable, "-c", code], env=env, check=False)
    except OSError as exc:  # no process to be had here (a sandbox, a frozen program)
        return f"no process to compile in ({exc})"
    return None if done.returncode == 0 else f"the compiling process failed (exit code {done.returncode})"


def _compile_child(module: str, name: str, parent: int) -> None:
    """:func:`compile_elsewhere`'s child: runs ``module.name()``, and exits at once when ``parent`` has gone (a
    server stopped or killed while the kernels compile, minutes on a first start, leaves no compiler behind)."""
    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, name="svelive-compile-watch", daemon=True).start()
    getattr(importlib.import_module(module), name)()


@functools.cache
def unmap_libraries_after_loads() -> None:
    """From now on, whenever numba has loaded or compiled kernels (its compiler lock released by its outermost
    holder), unmap this process's pages of the libraries it maps (:class:`svelive.memory.LibraryPages`): the pages
    in use come back on their next touch. Once per process (repeat calls do nothing).

    Loading a kernel from the cache runs LLVM; running one does not. A long-running process loads its kernels as
    frames first need them and then seldom again, yet kept resident every page of LLVM's library that loading it
    (at import) and the loads had touched, and of the other libraries those their start had touched (the
    monochrome server, 1920x1200, 10 clients: 191 MiB of file pages, 98 after numba's loads unmapped LLVM's).
    """
    from numba.core import event
    from numba.core.compiler_lock import global_compiler_lock

    from svelive.memory import LibraryPages

    pages = LibraryPages()

    class Unmap(event.Listener):
        def on_start(self, ev: event.Event) -> None:
            pass

        def on_end(self, ev: event.Event) -> None:
            if not global_compiler_lock.is_locked():
                pages.unmap()

    event.register("numba:compiler_lock", Unmap())
    pages.unmap()


def flat(*arrays: np.ndarray) -> list[np.ndarray]:
    """1-D views of C-contiguous arrays (a copy only for a non-contiguous one), for kernels that loop once."""
    return [a.reshape(-1) for a in arrays]


@intrinsic
def fma32(typingctx, a, b, c):
    """a b + c rounded once (float32), inside kernels: where a kernel must round as other code does (OpenCV's
    vectorised filters and resizes take a fused multiply-add per tap); numba itself never fuses."""
    def codegen(context, builder, signature, args):
        return builder.fma(*args)
    return types.float32(types.float32, types.float32, types.float32), codegen
