"""CPU priority of the threads that only publish frames.

Every frame goes through the capture and reconstruction threads in turn: they
set the frame rate. The publishers (the preview's tone map and JPEG, the RTSP
stream's I420 conversion and H.264 encoder) take each frame after it. When more
threads want to run than there are cores, the scheduler shares the cores out,
so a publisher's turn can delay the next frame's reconstruction and cost a
frame. Run a few nice levels lower (``publisher_nice``), the publishers take a
smaller share, and the cost is a little latency, not frames.

The reconstruction leaves a core idle for part of each frame (while one thread
does the serial steps, or waits for a frame), and the preview's encoder thread
belongs there: under Linux's ``SCHED_IDLE`` policy (``publisher_idle``) a
thread runs only on a core no other thread wants, and yields it as soon as one
wakes. But it then gets next to nothing while other processes keep every core
busy, so :class:`EncoderPriority` uses the policy only where the thread may
leave it again (``CAP_SYS_NICE``, or an ``RLIMIT_NICE`` that allows its nice
value), and leaves it for a while whenever a frame's encoding waited long for
a core.

Linux keeps a policy and a nice value for each thread, and a new thread starts
with its creator's: lowering GStreamer's streaming thread before the H.264
encoder starts its own threads lowers those as well.
"""

from __future__ import annotations

import os
import resource
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

CAP_SYS_NICE = 23  # the capability's bit in /proc/<pid>/status's CapEff (linux/capability.h)


def lower_publisher(steps: int) -> int | None:
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


def may_leave_idle(nice: int, status: str | None = None, nice_limit: int | None = None) -> bool:
    """Whether a thread at ``nice`` could return from ``SCHED_IDLE`` to the normal policy: Linux asks for
    ``CAP_SYS_NICE`` (in ``status``'s CapEff; default: this process's /proc/self/status) or an ``RLIMIT_NICE``
    soft limit (``nice_limit``; default: this process's) of at least 20 - ``nice``."""
    if sys.platform != "linux":
        return False
    if nice_limit is None:
        nice_limit = resource.getrlimit(resource.RLIMIT_NICE)[0]
    if nice_limit == resource.RLIM_INFINITY or nice_limit >= 20 - nice:
        return True
    if status is None:
        try:
            with open("/proc/self/status") as f:
                status = f.read()
        except OSError:
            return False
    for line in status.splitlines():
        if line.startswith("CapEff:"):
            return bool(int(line.split()[1], 16) >> CAP_SYS_NICE & 1)
    return False


def _set_policy(idle: bool) -> bool:
    """Put the calling thread under ``SCHED_IDLE`` (``idle``) or the normal policy, keeping its nice value;
    False if the system refused."""
    try:
        os.sched_setscheduler(threading.get_native_id(), os.SCHED_IDLE if idle else os.SCHED_OTHER,
                              os.sched_param(0))
        return True
    except OSError:
        return False


@dataclass
class EncoderPriority:
    """The preview encoder thread's priority: ``nice_steps`` below the reconstruction, and under ``SCHED_IDLE``
    when ``idle`` is asked and the thread may leave it again (:func:`may_leave_idle`).

    Call :meth:`enter` on the thread once, then :meth:`after_frame` after each frame with its encoding's wall
    and thread CPU time: a frame whose wall exceeded its CPU by ``starved_s`` (the thread waited that long for a
    core: other processes keep the cores busy) moves the thread to the normal policy (at its nice value) for
    ``hold_s``, after which it tries ``SCHED_IDLE`` again. A fallback within ``hold_s`` of that return doubles the
    next hold (up to ``hold_s`` x 2^``max_doublings``): under a lasting load the previews are not stalled every
    ``hold_s`` (each stall lasts until a frame is encoded, a few seconds with every core taken).

    Attributes (read by the state): ``active``, the thread runs under ``SCHED_IDLE`` now; ``fallbacks``, how many
    times it left it for ``hold_s``; ``nice``, its nice value (None where unknown).
    """

    nice_steps: int
    idle: bool
    starved_s: float = 0.25
    hold_s: float = 10.0
    max_doublings: int = 5
    clock: Callable[[], float] = time.monotonic
    active: bool = field(default=False, init=False)
    fallbacks: int = field(default=0, init=False)
    nice: int | None = field(default=None, init=False)
    _allowed: bool = field(default=False, init=False)
    _normal_until: float = field(default=0.0, init=False)
    _doublings: int = field(default=0, init=False)

    def enter(self) -> None:
        """On the encoder thread: lower it."""
        self.nice = lower_publisher(self.nice_steps)
        self._allowed = self.idle and self.nice is not None and may_leave_idle(self.nice)
        self.active = self._allowed and _set_policy(True)

    def after_frame(self, wall_s: float, cpu_s: float) -> None:
        """On the encoder thread, after a frame's encoding took ``wall_s`` seconds of wall and ``cpu_s`` of the
        thread's CPU."""
        if not self._allowed:
            return
        now = self.clock()
        if self.active and wall_s - cpu_s > self.starved_s:
            if _set_policy(False):
                recent = self.fallbacks > 0 and now - self._normal_until < self.hold_s
                self._doublings = min(self._doublings + 1, self.max_doublings) if recent else 0
                self.active = False
                self.fallbacks += 1
                self._normal_until = now + self.hold_s * 2 ** self._doublings
        elif not self.active and now >= self._normal_until:
            self.active = _set_policy(True)

    def public(self) -> dict:
        """The JSON state's view."""
        return {"nice": self.nice, "idle_asked": self.idle, "idle": self.active, "idle_fallbacks": self.fallbacks}
