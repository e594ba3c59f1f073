"""The allocator policy: freed frame buffers are reused, not page-faulted in anew every frame."""

import subprocess
import sys

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
