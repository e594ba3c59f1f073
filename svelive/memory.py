"""The process's allocator policy: keep freed frame buffers for the next frame, hand them back on request.

A live stream allocates a few dozen whole-frame arrays per frame (9 MB each at
1920x1200 float32) and frees them a frame later. glibc's malloc serves arrays
that large with fresh ``mmap`` pages, or trims them off the heap's top when
freed, so every frame pays their page faults again: measured on the demo's
1920x1200 frames, about a fifth of the reconstruction's time went to the kernel
(``benchmarks/live_cost.py``). :func:`keep_freed_memory` makes freed buffers
stay in the heap for reuse; :func:`release_memory` returns them after a burst
that will not repeat (a calibration). Elsewhere than glibc both do nothing.

Kept buffers are kept per malloc arena, and glibc gives threads arenas of their own (up to
8 per core): the reconstruction's strip workers, the encoder and the server's threads each
kept their own frame's worth of freed buffers, so the resident memory grew with the number
of threads that ever touched a frame-sized array. :func:`keep_freed_memory` therefore also
makes every thread share one arena (measured with ``benchmarks/service.py``: 1920x1200 mono,
10 clients, resident memory 829 -> 697 MB, frame rate within the run's noise): the
allocations it serves are frame-sized and few (dozens a frame), so threads seldom wait on its
lock, and small Python objects do not use it (pymalloc).

A process's libraries count in its resident memory with every page it has touched and not let go:
:class:`LibraryPages` unmaps them after the start's bursts (numba loading kernels: ``svelive.jit``), the pages
in use coming back on their next touch.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import mmap
import re
import threading

import numpy as np

#: mallopt parameters (glibc's malloc.h)
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _M_ARENA_MAX = -1, -3, -8
#: madvise advice (Linux's mman.h): unmap the range's pages; a file's come back from the page cache when touched
_MADV_DONTNEED = 4
#: A mapping's first line in /proc/PID/smaps: start-end perms offset device inode [path]
_SMAPS_MAPPING = re.compile(r"^([0-9a-f]+)-([0-9a-f]+) (\S{4}) \S+ \S+ \d+ *(.*)$")
#: Largest block glibc accepts as an mmap threshold on 64-bit systems (32 MiB): arrays up to that size (a
#: 1920x1200x3 float32 image is 27.6 MB) come from the heap and are reused.
MMAP_THRESHOLD = 32 * 1024 * 1024
#: Free memory at the heap's top kept rather than returned: a frame's worth of temporaries and more.
TRIM_THRESHOLD = 512 * 1024 * 1024


def _libc() -> ctypes.CDLL | None:
    name = ctypes.util.find_library("c")
    try:
        return ctypes.CDLL(name) if name else None
    except OSError:
        return None


def keep_freed_memory(arenas: int = 1) -> bool:
    """Make malloc keep freed frame-sized buffers for reuse (glibc), in at most ``arenas`` arenas shared by all
    threads (0: glibc's own limit); True when the policy was set.

    Call once at the start of a long-running stream (``svelive serve``, ``reconstruct-sequence``), before it
    starts its threads: a thread keeps the arena it first allocated from. The resident memory then stays at
    the stream's peak instead of rising and falling every frame.
    """
    libc = _libc()
    if libc is None or not hasattr(libc, "mallopt"):
        return False
    return (bool(libc.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD))
            and bool(libc.mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
            and (arenas <= 0 or bool(libc.mallopt(_M_ARENA_MAX, arenas))))


def outside_heap(shape: tuple[int, ...], dtype: np.dtype | type) -> np.ndarray:
    """An uninitialised array in pages of its own (an anonymous mapping), handed back to the system as soon as the
    array goes, never kept in malloc's heap.

    For whole-frame buffers a stream makes seldom, which :func:`keep_freed_memory` would otherwise keep: a
    noise tracker reads three frames in every 64 to 512 (``svelive.noise.NoiseTracker``); from the heap, its frames
    and their temporaries added to the heap's peak, which a process then keeps resident for good. Pages are
    zero-filled when first written (a fault each), which is why a stream's every-frame buffers stay in the heap.
    """
    private, anonymous = getattr(mmap, "MAP_PRIVATE", None), getattr(mmap, "MAP_ANONYMOUS", None)
    if private is None or anonymous is None:  # (not a POSIX system: the heap, as numpy allocates)
        return np.empty(shape, dtype)
    count = int(np.prod(shape, dtype=np.int64))
    dtype = np.dtype(dtype)
    pages = mmap.mmap(-1, max(count * dtype.itemsize, 1), flags=private | anonymous)
    return np.frombuffer(pages, dtype, count).reshape(shape)


def release_memory() -> None:
    """Hand freed heap back to the system after a burst of allocations that will not repeat.

    A calibration's fit allocates hundreds of MB of short-lived numpy arrays in a worker
    thread; glibc keeps freed chunks in that thread's arena (all the more under
    :func:`keep_freed_memory`), so the process's resident memory stayed up after every
    calibration. ``malloc_trim(0)`` returns the free pages of every arena.
    """
    gc.collect()
    libc = _libc()
    if libc is not None and hasattr(libc, "malloc_trim"):
        libc.malloc_trim(0)


def read_only_file_mappings() -> list[tuple[int, int]]:
    """This process's mappings of files that it only reads and holds no private copy in (libraries' code and
    constants, not their relocated data): (start, end) addresses, for :func:`unmap_pages`; [] where not Linux.

    A mapping with private copies (``Anonymous`` > 0 in ``/proc/self/smaps``), a writable one or a device's is
    left out: unmapping a private copy would lose it. Without write permission none is made later, so the list
    stays valid while the files stay mapped.
    """
    try:
        with open("/proc/self/smaps") as f:
            lines = f.read().splitlines()
    except OSError:
        return []
    ranges, current = [], None
    for line in lines:
        mapping = _SMAPS_MAPPING.match(line)
        if mapping is not None:
            start, end, perms, path = mapping.groups()
            wanted = path.startswith("/") and not path.startswith("/dev/") and "w" not in perms
            current = (int(start, 16), int(end, 16)) if wanted else None
        elif current is not None and line.startswith("Anonymous:"):
            if int(line.split()[1]) == 0:
                ranges.append(current)
            current = None
    return ranges


def unmap_pages(ranges: list[tuple[int, int]]) -> int:
    """Unmap this process's resident pages in ``ranges`` (of :func:`read_only_file_mappings`); the bytes advised.

    The pages stay in the page cache and come back on the next touch (a minor fault), so only the pages in use
    are resident again.
    """
    libc = _libc()
    if libc is None or not hasattr(libc, "madvise"):
        return 0
    madvise = libc.madvise
    madvise.argtypes, madvise.restype = (ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int), ctypes.c_int
    return sum(end - start for start, end in ranges if madvise(start, end - start, _MADV_DONTNEED) == 0)


class LibraryPages:
    """Unmaps the pages of the files this process maps read-only (:func:`unmap_pages` over
    :func:`read_only_file_mappings`), for a process that touches much more of its libraries while it starts than
    while it runs: what it uses comes back on the next touch, the rest leaves its resident memory.

    Linux 6.18 caches files in large folios (up to 2 MiB on ext4) and maps a whole folio on a fault, so a library's
    resident pages are those of every folio the process ever touched: in the monochrome server (1920x1200) LLVM's
    library (libllvmlite, used only to load kernels) 95 MiB against 69 with 4 KiB pages, OpenCV's 39 against 13.
    The mappings are listed again (``/proc/self/smaps``, 15-40 ms) only when the mapped files changed
    (``/proc/self/maps``, well under a millisecond). Thread-safe.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._mapped: list[str] | None = None
        self._ranges: list[tuple[int, int]] = []

    def unmap(self) -> int:
        """Unmap the pages; the bytes of address space advised (0 where not Linux)."""
        try:
            with open("/proc/self/maps") as f:
                mapped = [line for line in f if " /" in line]
        except OSError:
            return 0
        with self._lock:
            if mapped != self._mapped:
                self._mapped, self._ranges = mapped, read_only_file_mappings()
            return unmap_pages(self._ranges)
