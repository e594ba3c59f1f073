"""CPU priority of the threads that only publish frames.

Every frame goes through the capture and reconstruction threads in turn: they
set the frame rate. The publishers (the preview's tone map and JPEG, the RTSP
stream's I420 conversion and H.264 encoder) take each frame after it. When more
threads want to run than there are cores, the scheduler shares the cores out
evenly, so a publisher's turn can delay the next frame's reconstruction and
cost a frame. Run a few nice levels lower, the publishers take the time the
reconstruction leaves (while it waits for a frame or for its strips) and the
cost is a little latency, not frames.

Linux keeps a nice value for each thread, and a new thread starts with its
creator's: lowering GStreamer's streaming thread before the H.264 encoder
starts its own threads lowers those as well.
"""

from __future__ import annotations

import os
import sys
import threading


def publisher_nice(steps: int) -> int | None:
    """Run the calling thread ``steps`` nice levels below the process's main thread (Linux; capped at 19).

    Idempotent, and never raises the thread's priority: a thread already at or below the target is left as it
    is (a GStreamer pool thread reused for a new media is not lowered twice). ``steps`` 0 changes nothing.
    Returns the thread's nice value, or None where threads have no nice value of their own (not Linux) or the
    system refused (a thread at a lower priority still works)."""
    if sys.platform != "linux":
        return None
    tid = threading.get_native_id()
    try:
        nice = os.getpriority(os.PRIO_PROCESS, tid)
        target = min(19, os.getpriority(os.PRIO_PROCESS, os.getpid()) + steps)
        if steps > 0 and nice < target:
            os.setpriority(os.PRIO_PROCESS, tid, target)
            nice = target
        return nice
    except OSError:
        return None
