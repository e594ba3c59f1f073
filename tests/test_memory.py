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
