"""Measurement of the pipeline's threads: rates, latencies, drops (the hand-offs are in ``handoff``).

Every class here is thread-safe: one thread writes, any thread reads.
"""

from __future__ import annotations

import bisect
import collections
import itertools
import threading
import time

import numpy as np

#: Samples kept per latency / rate window.
WINDOW = 256


class RateMeter:
    """Events per second over the last WINDOW events (0 when the last one is older than ``stale_s``)."""

    def __init__(self, stale_s: float = 2.0) -> None:
        self._times: collections.deque[int] = collections.deque(maxlen=WINDOW)
        self._lock = threading.Lock()
        self.count = 0
        self.stale_s = stale_s

    def tick(self, now_ns: int | None = None) -> None:
        with self._lock:
            self._times.append(time.monotonic_ns() if now_ns is None else now_ns)
            self.count += 1

    def rate(self) -> float:
        with self._lock:
            times = list(self._times)
        if len(times) < 2 or (time.monotonic_ns() - times[-1]) / 1e9 > self.stale_s:
            return 0.0
        # over the last two seconds at most, so a rate change shows quickly
        recent = [t for t in times if times[-1] - t <= 2e9]
        if len(recent) < 2:
            return 0.0
        return (len(recent) - 1) / ((recent[-1] - recent[0]) / 1e9)


#: Upper bounds (ms) of the latency histograms' buckets (Prometheus-style, cumulative; +Inf implied).
LATENCY_BUCKETS_MS = (1, 2, 5, 10, 20, 33, 50, 75, 100, 150, 200, 300, 500, 1000, 2000, 5000)


class LatencyWindow:
    """Durations in ms of one stage: the recent ones summarised as p50 / p95 / max, and all of them
    since start counted in :data:`LATENCY_BUCKETS_MS` (for /metrics)."""

    def __init__(self) -> None:
        self._values: collections.deque[float] = collections.deque(maxlen=WINDOW)
        self._lock = threading.Lock()
        self._buckets = [0] * len(LATENCY_BUCKETS_MS)
        self._sum = 0.0
        self._count = 0

    def add(self, ms: float) -> None:
        with self._lock:
            self._values.append(ms)
            self._sum += ms
            self._count += 1
            index = bisect.bisect_left(LATENCY_BUCKETS_MS, ms)
            if index < len(self._buckets):
                self._buckets[index] += 1

    def summary(self) -> dict[str, float] | None:
        with self._lock:
            values = np.array(self._values, dtype=np.float64)
        if values.size == 0:
            return None
        p50, p95 = np.percentile(values, [50, 95])
        return {"p50": round(float(p50), 2), "p95": round(float(p95), 2), "max": round(float(values.max()), 2),
                "n": int(values.size)}

    def histogram(self) -> tuple[list[tuple[float, int]], float, int]:
        """(cumulative counts [(upper bound ms, count of durations <= it)], sum ms, count) since start."""
        with self._lock:
            counts, total, n = list(self._buckets), self._sum, self._count
        return list(zip(map(float, LATENCY_BUCKETS_MS), itertools.accumulate(counts))), total, n


class DropCounter:
    """Frames dropped by each stage, counted by cause (``reconstruct_busy``, ``encoder_busy``, ...)."""

    def __init__(self) -> None:
        self._counts: collections.Counter = collections.Counter()
        self._lock = threading.Lock()

    def count(self, cause: str, n: int = 1) -> None:
        with self._lock:
            self._counts[cause] += n

    def snapshot(self) -> dict[str, int]:
        """The counts so far, by cause, in the order the causes first occurred."""
        with self._lock:
            return dict(self._counts)
