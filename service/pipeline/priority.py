"""CPU priority of the threads that only publish frames.

Every frame goes through the capture and reconstruction threads in turn: they
set the frame rate. The publishers (the preview's tone map and JPEG, the RTSP
stream's I420 conversion and H.264 encoder) take each frame after it. When more
threads want to run than there are cores, the scheduler shares the cores out,
so a publisher's turn can delay the next frame's reconstruction and cost a
frame. The reconstruction leaves a core idle for part of each frame (while
one thread does the serial steps, or waits for a frame): the publishers belong
there. Under Linux's ``SCHED_IDLE`` policy (the default) a thread runs only on
a core no other thread wants, and yields it at once when one wakes; a few nice
levels lower (``publisher_nice``, also where the idle policy is off or
refused) only shrink its share. Either way the cost is a little latency, not
frames.

Linux keeps a policy and a nice value for each thread, and a new thread starts
with its creator's: lowering GStreamer's streaming thread before the H.264
encoder starts its own threads lowers those as well.
"""

from __future__ import annotations

import os
import sys
import threading


def lower_publisher(steps: int, idle: bool) -> tuple[int, bool] | None:
    """Run the calling thread ``steps`` nice levels below the process's main thread (capped at 19) and, if
    ``idle``, under the ``SCHED_IDLE`` policy (Linux).

    Idempotent, and never raises the thread's priority: a thread already at or below the target nice value is
    left at its own (a GStreamer pool thread reused for a new media is not lowered twice); ``steps`` 0 and
    ``idle`` False change nothing. Returns (the thread's nice value, whether it runs under ``SCHED_IDLE``), or
    None where threads have no priority of their own (not Linux) or the system refused (a thread at a lower
    priority still works)."""
    if sys.platform != "linux":
        return None
    tid = threading.get_native_id()
    try:
        nice = os.getpriority(os.PRIO_PROCESS, tid)
        target = min(19, os.getpriority(os.PRIO_PROCESS, os.getpid()) + steps)
        if steps > 0 and nice < target:
            os.setpriority(os.PRIO_PROCESS, tid, target)
            nice = target
        if idle and os.sched_getscheduler(tid) != os.SCHED_IDLE:
            os.sched_setscheduler(tid, os.SCHED_IDLE, os.sched_param(0))
        return nice, os.sched_getscheduler(tid) == os.SCHED_IDLE
    except OSError:
        return None
