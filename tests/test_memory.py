"""The allocator policy: freed frame buffers are reused, not page-faulted in anew every frame; libraries' pages
unmapped after numba's loads."""

import subprocess
import sys

import pytest

FRAMES = """
import resource, sys
import numpy as np
if sys.argv[1] == "keep":
    from svelive.memory import keep_freed_memory
    assert keep_freed_memory()
def frame():
    arrays = [np.ones((1200, 1920), np.float32) for _ in range(6)]  # a frame's temporaries, 9 MB each
    return float(sum(a[0, 0] for a in arrays))
frame()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(10):
    frame()
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _faults(policy: str) -> int:
    done = subprocess.run([sys.executable, "-c", FRAMES, policy], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return int(done.stdout)


def test_kept_buffers_are_reused_without_page_faults():
    default, kept = _faults("default"), _faults("keep")
    # 10 frames of 6 x 9 MB (2250 pages each): glibc's default trims the heap and faults pages in again
    assert default > 10 * 2250
    assert kept < default / 10


def test_policy_calls_are_safe_to_repeat():
    # in a child: the policy is the whole process's, and the test process must keep glibc's default
    code = ("from svelive.memory import keep_freed_memory, release_memory\n"
            "print(keep_freed_memory(), keep_freed_memory()); release_memory(); release_memory()")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0 and done.stdout.split() == ["True", "True"], done.stderr


THREADS = """
import sys, threading
import numpy as np
from svelive.memory import keep_freed_memory
assert keep_freed_memory(arenas=int(sys.argv[1]))
turn = threading.Lock()  # one frame alive at a time, as the pipeline's stages hand frames on
def frames():
    for _ in range(3):
        with turn:
            arrays = [np.ones((1200, 1920), np.float32) for _ in range(6)]  # a frame's temporaries, 9 MB each
            del arrays
workers = [threading.Thread(target=frames) for _ in range(4)]  # long-lived, like the strip workers and encoder
for t in workers:
    t.start()
for t in workers:
    t.join()
print(next(int(line.split()[1]) for line in open("/proc/self/status") if line.startswith("RssAnon:")))
"""


def _resident_kb(arenas: int) -> int:
    done = subprocess.run([sys.executable, "-c", THREADS, str(arenas)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return int(done.stdout)


def test_threads_share_one_arena_of_kept_buffers():
    # 4 threads in turn free a frame's 55 MB: in arenas of their own each keeps one, in one arena the next reuses it
    shared, own = _resident_kb(1), _resident_kb(0)
    frame_kb = 6 * 1200 * 1920 * 4 // 1024
    assert shared < own - 2 * frame_kb, (shared, own)


OUTSIDE = """
import sys
import numpy as np
from svelive.memory import keep_freed_memory, outside_heap
assert keep_freed_memory()
def anon():
    return next(int(line.split()[1]) for line in open("/proc/self/status") if line.startswith("RssAnon:"))
before = anon()
a = outside_heap((1200, 1920), np.float32) if sys.argv[1] == "outside" else np.empty((1200, 1920), np.float32)
a[...] = 1.5
assert a.shape == (1200, 1920) and a.dtype == np.float32 and a.flags.writeable and float(a.sum()) == 1.5 * a.size
held = anon()
del a
print(held - before, anon() - before)
"""


def test_a_buffer_outside_the_heap_goes_back_to_the_system_when_dropped():
    # in a child: a 9 MB frame from the heap stays resident once freed (the policy), one outside it does not
    out = {}
    for where in ("outside", "heap"):
        done = subprocess.run([sys.executable, "-c", OUTSIDE, where], capture_output=True, text=True, timeout=60)
        assert done.returncode == 0, done.stderr
        out[where] = [int(v) for v in done.stdout.split()]
    frame_kb = 1200 * 1920 * 4 // 1024
    assert out["outside"][0] > 0.9 * frame_kb and out["heap"][0] > 0.9 * frame_kb
    assert out["outside"][1] < 0.1 * frame_kb
    assert out["heap"][1] > 0.9 * frame_kb


LIBRARIES = """
import sys
import numpy as np
import numba
if sys.argv[1] == "unmap":
    from svelive.jit import unmap_libraries_after_loads
    unmap_libraries_after_loads()
    unmap_libraries_after_loads()  # once a process: a second call registers nothing more
def resident_kb(name):
    total, mine = 0, False
    for line in open("/proc/self/smaps"):
        if line[0] in "0123456789abcdef" and "-" in line.split()[0]:
            mine = name in line
        elif mine and line.startswith("Rss:"):
            total += int(line.split()[1])
    return total
@numba.njit
def dot(a, b):
    s = 0.0
    for i in range(a.size):
        s += a[i] * b[i]
    return s
x = np.arange(1000, dtype=np.float64)
assert dot(x, x) == float(x @ x)  # compiled in this process: LLVM runs, then (unmap) its pages are unmapped
print(resident_kb("libllvmlite"), resident_kb("_multiarray_umath"))
"""


def _library_kb(policy: str) -> list[int]:
    done = subprocess.run([sys.executable, "-c", LIBRARIES, policy], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return [int(v) for v in done.stdout.split()]


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/self/smaps and madvise: Linux")
def test_library_pages_unmapped_after_numba_compiles_and_come_back_on_use():
    # in a child: LLVM's library keeps tens of MB resident after a compile, unless unmapped after it; numpy's
    # pages, unmapped too, came back as the child used numpy after the compile (and its results are right)
    kept_llvm, kept_numpy = _library_kb("keep")
    unmapped_llvm, unmapped_numpy = _library_kb("unmap")
    assert kept_llvm > 20 * 1024, kept_llvm
    assert unmapped_llvm < kept_llvm / 5, (unmapped_llvm, kept_llvm)
    assert unmapped_numpy > 0


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/self/smaps and madvise: Linux")
def test_only_read_only_file_mappings_without_private_copies_are_listed():
    from svelive.memory import read_only_file_mappings

    writable, private = set(), set()
    start = None
    for line in open("/proc/self/smaps"):
        fields = line.split()
        if line[0] in "0123456789abcdef" and "-" in fields[0]:
            start = int(fields[0].split("-")[0], 16)
            if "w" in fields[1] or len(fields) < 6 or not fields[5].startswith("/"):
                writable.add(start)
        elif line.startswith("Anonymous:") and int(fields[1]) > 0:
            private.add(start)
    listed = {start for start, _ in read_only_file_mappings()}
    assert listed  # the interpreter's and numpy's code at least
    assert not listed & writable and not listed & private
