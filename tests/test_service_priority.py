"""The publishers' CPU priority (service.pipeline.priority): nice levels, and the encoder's SCHED_IDLE with its
way back when other processes keep it from a core."""

from __future__ import annotations

import os
import sys
import threading
import time

import pytest

from service.pipeline import Pipeline, PipelineConfig
from service.pipeline.priority import EncoderPriority, lower_publisher, may_leave_idle
from tests.test_service_helpers import SimSource, make_camera

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="threads have priorities of their own on Linux only")


def threads_priority() -> dict[int, tuple[str, int, bool]]:
    """Every thread of this process: native id -> (its kernel name, its nice value, whether it runs under
    ``SCHED_IDLE``)."""
    out = {}
    for tid in map(int, os.listdir("/proc/self/task")):
        try:
            with open(f"/proc/self/task/{tid}/comm") as f:
                out[tid] = (f.read().strip(), os.getpriority(os.PRIO_PROCESS, tid),
                            os.sched_getscheduler(tid) == os.SCHED_IDLE)
        except OSError:  # the thread ended meanwhile
            pass
    return out


def _own() -> tuple[int, bool]:
    """The calling thread's (nice value, under SCHED_IDLE)."""
    return threads_priority()[threading.get_native_id()][1:]


def _on_a_thread(body) -> list:
    """Run ``body(seen)`` on a new thread (whose priority dies with it) and return what it appended."""
    seen: list = []
    errors: list = []

    def run() -> None:
        try:
            body(seen)
        except BaseException as error:  # handed to the test's thread
            errors.append(error)

    thread = threading.Thread(target=run)
    thread.start()
    thread.join(10)
    assert not thread.is_alive() and not errors, errors
    return seen


@pytest.mark.parametrize("steps", [0, 3, 30])
def test_a_publisher_is_lowered_as_configured_and_only_once(steps):
    base = os.getpriority(os.PRIO_PROCESS, os.getpid())

    def body(seen):
        seen.append(lower_publisher(steps))
        seen.append(lower_publisher(steps))  # idempotent: a reused thread is not lowered twice
        seen.append(_own())

    want = min(19, base + steps)
    assert _on_a_thread(body) == [want, want, (want, False)]
    assert _own() == (base, False)  # the caller's own thread: untouched


STATUS = "Name:\tpython\nCapInh:\t0000000000000000\nCapEff:\t{:016x}\n"


@pytest.mark.parametrize("capabilities, limit, nice, may", [
    (1 << 23, 0, 5, True),  # CAP_SYS_NICE
    ((1 << 64) - 1 - (1 << 23), 0, 5, False),  # every capability but that one
    (0, 15, 5, True),  # RLIMIT_NICE 15 allows nice 5 (20 - 15)
    (0, 14, 5, False),
    (0, 1, 19, True),
])
def test_whether_a_thread_may_leave_sched_idle(capabilities, limit, nice, may):
    assert may_leave_idle(nice, STATUS.format(capabilities), limit) is may


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


@pytest.mark.skipif(not may_leave_idle(min(19, os.getpriority(os.PRIO_PROCESS, os.getpid()) + 5)),
                    reason="this process may not leave SCHED_IDLE (no CAP_SYS_NICE, RLIMIT_NICE too low)")
def test_the_encoder_leaves_sched_idle_while_it_waits_for_a_core_and_comes_back():
    clock = Clock()
    nice = min(19, os.getpriority(os.PRIO_PROCESS, os.getpid()) + 5)
    priority = EncoderPriority(5, True, starved_s=0.25, hold_s=10.0, clock=clock)

    def body(seen):
        priority.enter()
        seen.append((_own(), priority.active))
        priority.after_frame(0.2, 0.01)  # waited 0.19 s: not starved
        seen.append((_own(), priority.active))
        priority.after_frame(0.5, 0.01)  # waited 0.49 s for a core
        seen.append((_own(), priority.active, priority.fallbacks))
        clock.now += 9.9
        priority.after_frame(0.01, 0.01)  # within hold_s: stays at the normal policy
        seen.append((_own(), priority.active))
        clock.now += 0.2
        priority.after_frame(0.01, 0.01)  # after it: SCHED_IDLE again
        seen.append((_own(), priority.active, priority.fallbacks))
        clock.now += 5.0
        priority.after_frame(1.0, 0.01)  # starved again soon after: the next hold is twice as long
        clock.now += 19.9
        priority.after_frame(0.01, 0.01)
        seen.append((_own(), priority.active, priority.fallbacks))
        clock.now += 0.2
        priority.after_frame(0.01, 0.01)
        seen.append((_own(), priority.active))
        clock.now += 60.0
        priority.after_frame(1.0, 0.01)  # starved long after its return: back to a hold of 10 s
        clock.now += 10.1
        priority.after_frame(0.01, 0.01)
        seen.append((_own(), priority.active, priority.fallbacks))

    assert _on_a_thread(body) == [((nice, True), True), ((nice, True), True), ((nice, False), False, 1),
                                  ((nice, False), False), ((nice, True), True, 1), ((nice, False), False, 2),
                                  ((nice, True), True), ((nice, True), True, 3)]
    assert priority.public() == {"nice": nice, "idle_asked": True, "idle": True, "idle_fallbacks": 3}


def test_without_idle_asked_the_encoder_keeps_the_normal_policy():
    priority = EncoderPriority(2, False)

    def body(seen):
        priority.enter()
        priority.after_frame(5.0, 0.01)
        seen.append((_own(), priority.active, priority.fallbacks))

    nice = min(19, os.getpriority(os.PRIO_PROCESS, os.getpid()) + 2)
    assert _on_a_thread(body) == [((nice, False), False, 0)]


@pytest.mark.skipif(not may_leave_idle(min(19, os.getpriority(os.PRIO_PROCESS, os.getpid()) + 5)),
                    reason="this process may not leave SCHED_IDLE (no CAP_SYS_NICE, RLIMIT_NICE too low)")
def test_a_pipeline_asked_for_it_runs_its_encoder_under_sched_idle():
    camera = make_camera(fps=20.0, n=1, shape=(96, 128))
    config = PipelineConfig(source="sim", temporal=False, publisher_idle=True)
    with Pipeline(config, lambda: SimSource(camera)) as pipeline:
        pipeline.watch(+1)
        try:
            start = pipeline.encoded.count
            deadline = time.monotonic() + 60
            while pipeline.encoded.count < start + 2 and time.monotonic() < deadline:
                time.sleep(0.05)
            encoder = {t.name: t.native_id for t in threading.enumerate()}["svelive-encode"]
            priority = threads_priority()[encoder][1:]
            state = pipeline.encoder.priority.public()
        finally:
            pipeline.watch(-1)
    assert pipeline.encoded.count >= start + 2  # previews made under the policy
    nice = min(19, os.getpriority(os.PRIO_PROCESS, os.getpid()) + 5)
    assert priority == (nice, True)
    assert state == {"nice": nice, "idle_asked": True, "idle": True, "idle_fallbacks": 0}
