"""The live-quality ladder: which reconstruction setting runs while the machine cannot keep the camera's rate.

A live view that silently shows a third of the camera's frames is not monitoring.
When the reconstruction falls behind the camera (a bigger sensor, a smaller
machine, more cameras, a busy neighbour), the service steps down a declared
ladder of live settings, each cheaper than the one above, and steps back up
when there is headroom; ``/api/state``, ``/metrics`` and the viewer say which
step runs and why. ``--live-quality fixed`` keeps the configured setting and
only reports that it is behind.

:class:`LiveQuality` is a small state machine fed, once per published frame,
with counters the pipeline keeps anyway (frames arrived, frames dropped because
the reconstruction was busy, the reconstruction's wall time). It holds no
thread and no clock of its own, so tests drive it with made-up times.
"""

from __future__ import annotations

import statistics
import threading
from collections import deque
from dataclasses import dataclass
from typing import Any

from svelive.reconstruction.live import LiveStep, ladder_for


@dataclass(frozen=True)
class QualityConfig:
    """When :class:`LiveQuality` steps.

    Attributes:
        window_s: the evidence window: frames arrived and lost over it.
        behind: share of the window's arrivals lost to a busy reconstruction that counts as falling behind
            (with at least ``min_lost`` frames, and the reconstruction's median time over the window above
            ``busy`` of the camera's frame interval: losses alone may be a burst, not a rate).
        min_lost: fewest lost frames in the window that count.
        busy: share of the frame interval the reconstruction's median time must exceed to count as behind.
        headroom: step up only when the step above is predicted (this step's time scaled by the steps'
            costs) to take at most this share of the camera's frame interval.
        hold_s: time without loss before trying the step above; doubled every time a step up had to be
            undone within ``hold_s`` of it, up to ``max_hold_s``.
        max_hold_s: the longest hold.
        cheaper: a step down goes to the first step below whose cost is under this share of the running step's
            (:meth:`LiveStep.cost_at`, the band refresh included): the declared costs were measured within about
            10 %, so a step that costs 0.97 of this one is not a step down.
    """

    window_s: float = 2.0
    behind: float = 0.1
    min_lost: int = 5
    busy: float = 0.85
    headroom: float = 0.8
    hold_s: float = 10.0
    max_hold_s: float = 160.0
    cheaper: float = 0.9


class LiveQuality:
    """Chooses the live step from what the stream shows; thread-safe (one writer, any reader).

    Down: when, over the last ``window_s``, more than ``behind`` of the camera's frames
    were dropped because the reconstruction was still busy and its median time is most
    of the frame interval; to the first step below that is cheaper (``cheaper``) than this
    one as it ran (a still view's top step skips most of the method with the band refresh,
    ``SequenceResult.method_rows``, and can cost less than the steps declared below it).
    Up: after ``hold`` seconds without such a loss, to the best step above predicted (by its
    cost when it last ran, else its declared one) to fit in ``headroom`` of the frame interval. After any change the window starts afresh (the new step's first frames
    pay for a new stream). A step up that is undone soon doubles the hold.
    """

    def __init__(self, method: str, temporal: bool, mode: str = "adaptive",
                 config: QualityConfig | None = None, parallel: int = 1) -> None:
        self.config = config or QualityConfig()
        self.parallel = max(1, parallel)  # frames reconstructed at once (PipelineConfig.parallel_frames)
        self._lock = threading.Lock()
        self.mode = mode
        self.steps = ladder_for(method, temporal, mode)
        self._index = 0
        self._reason = "the configured setting"
        self._changes = 0
        self._behind = False
        # (time ns, arrived, lost, reconstruct ms, method rows) per published frame of the current step
        self._samples: deque[tuple[int, int, int, float, float]] = deque()
        self._since_ns: int | None = None  # start of the current step's evidence
        self._hold_s = self.config.hold_s
        self._stepped_up_ns: int | None = None
        self._reconstruct_ms: float | None = None
        # each step's cost (LiveStep.cost_at) over the last window it ran: the band refresh makes a still view's
        # top step cheaper than its declared cost
        self._costs: dict[int, float] = {}

    def configure(self, method: str, temporal: bool) -> None:
        """A new configured setting (the user changed the method): back to its top step. The same setting
        again (a client that PUTs every setting) changes nothing."""
        with self._lock:
            steps = ladder_for(method, temporal, self.mode)
            if steps == self.steps:
                return
            self.steps = steps  # readers take the ladder and the index under the lock
            self._costs = {}
            self._moved(0, "the configured setting", None)
            self._hold_s, self._stepped_up_ns = self.config.hold_s, None

    @property
    def configured(self) -> LiveStep:
        """The configured setting: the ladder's top step."""
        with self._lock:
            return self.steps[0]

    @property
    def step(self) -> LiveStep:
        """The step that runs now (any thread)."""
        with self._lock:
            return self.steps[self._index]

    def _step(self) -> LiveStep:
        """:attr:`step` for a caller holding the lock."""
        return self.steps[self._index]

    def _moved(self, index: int, reason: str, now_ns: int | None) -> None:
        if index != self._index:
            self._changes += 1
        self._index, self._reason, self._behind = index, reason, False
        self._samples.clear()
        self._since_ns = now_ns
        self._reconstruct_ms = None

    def observe(self, now_ns: int, arrived: int, lost: int, reconstruct_ms: float, step: LiveStep,
                method_rows: float = 1.0) -> None:
        """One published frame: ``arrived`` and ``lost`` are running counts of the camera's frames and of those
        dropped because the reconstruction was busy; ``reconstruct_ms`` the frame's wall time; ``step`` the
        setting it was made with (frames of an earlier step are not evidence about this one); ``method_rows``
        the share of the frame's rows its method ran on (``SequenceResult.method_rows``: below 1 where the
        band refresh kept settled bands)."""
        c = self.config
        with self._lock:
            if step != self._step():
                return
            if self._since_ns is None:
                self._since_ns = now_ns
            self._samples.append((now_ns, arrived, lost, reconstruct_ms, method_rows))
            window_ns = int(c.window_s * 1e9)
            # the frames of the last window, and the one before it (frames slower than the window still judge)
            while len(self._samples) > 2 and self._samples[1][0] <= now_ns - window_ns:
                self._samples.popleft()
            t0, arrived0, lost0 = self._samples[0][:3]
            span_s = (now_ns - t0) / 1e9
            if span_s <= 0 or now_ns - self._since_ns < window_ns:
                return  # a window of this step's frames first
            new, dropped = arrived - arrived0, lost - lost0
            interval_ms = 1e3 * span_s / max(new, 1)
            # with several frames reconstructed at once, each takes up to that many frame intervals
            median = statistics.median(sample[3] for sample in self._samples) / self.parallel
            self._reconstruct_ms = median
            cost = self._step().cost_at(statistics.fmean(sample[4] for sample in self._samples))
            self._costs[self._index] = cost
            # losses alone could be a burst (a noise estimate, a collection); a reconstruction that takes most
            # of the frame interval is what cannot keep the rate
            self._behind = dropped >= c.min_lost and dropped > c.behind * new and median > c.busy * interval_ms
            if self._behind:
                self._step_down(now_ns, f"{dropped} of {new} frames dropped in {span_s:.1f} s: {self._step().name} "
                                        f"takes {median:.0f} ms of a {interval_ms:.0f} ms frame interval", cost)
            # a step up needs a window of frames that arrived steadily: not across a gap (a source offline)
            elif (self._index > 0 and not dropped and now_ns - self._since_ns >= self._hold_s * 1e9
                  and span_s <= 2 * c.window_s):
                # the best step predicted to fit: its cost when it last ran, else its declared one
                fits = [i for i in range(self._index)
                        if median * self._costs.get(i, self.steps[i].cost) / cost <= c.headroom * interval_ms]
                if fits:
                    self._stepped_up_ns = now_ns
                    self._moved(fits[0], f"headroom: {self._step().name} took {median:.0f} ms of a "
                                         f"{interval_ms:.0f} ms frame interval for {self._hold_s:.0f} s", now_ns)

    def _step_down(self, now_ns: int, reason: str, cost: float) -> None:
        """To the first step below whose cost (as it last ran, else declared) is under ``cheaper`` of ``cost``,
        this step's (a step within the costs' spread would not be cheaper)."""
        if self._stepped_up_ns is not None and now_ns - self._stepped_up_ns < self._hold_s * 1e9:
            self._hold_s = min(2 * self._hold_s, self.config.max_hold_s)  # that step up did not hold
        self._stepped_up_ns = None
        cheaper = [i for i in range(self._index + 1, len(self.steps)) if self._costs.get(i, self.steps[i].cost)
                   < self.config.cheaper * cost]
        if self.mode == "fixed" or not cheaper:
            self._reason = reason + (" (fixed: no step down)" if self.mode == "fixed" else
                                     " (lowest step)" if self._index + 1 >= len(self.steps) else " (no cheaper step)")
            return
        self._moved(cheaper[0], reason, now_ns)

    def state(self) -> dict[str, Any]:
        """JSON-ready: mode, the step that runs (index, name, method, temporal), the ladder, why, changes."""
        with self._lock:
            step = self._step()
            return {"mode": self.mode, "step": self._index, "name": step.name, "method": step.method,
                    "temporal": step.temporal, "steps": [s.name for s in self.steps], "reason": self._reason,
                    "behind": self._behind, "changes": self._changes, "hold_s": self._hold_s,
                    "reconstruct_ms": None if self._reconstruct_ms is None else round(self._reconstruct_ms, 1)}
