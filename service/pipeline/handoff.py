"""The hand-offs between the pipeline's threads and its publishers.

- :class:`Newest`: the newest item of a stream and its sequence number, read by any number of
  readers, each of which asks for an item newer than the last one it took and waits for one
  (in a thread, or on an asyncio event loop). A reader that is slower than the writer skips
  items; nothing is ever queued per reader (the uStreamer way: encode once, hand every client the
  newest frame). Every stage's output and every publisher's input is one of these.
- :class:`NewestSlot`: the one consuming hand-off, from the capture thread to the reconstruction
  threads: each frame is taken by exactly one reader, and the oldest one still unread makes room
  for a new one (``--queue`` frames at most), counted as dropped.

Both are thread-safe; ``put`` never blocks.
"""

from __future__ import annotations

import asyncio
import collections
import threading
from typing import Any, Generic, TypeVar

T = TypeVar("T")


class Newest(Generic[T]):
    """The newest item put, with its sequence number (1 for the first item, one more per ``put``).

    ``get_newest(after_seq, timeout)`` waits in the calling thread, ``await wait_newest(after_seq,
    timeout)`` on an event loop, for an item whose sequence number is above ``after_seq`` and returns
    ``(seq, item)`` of the newest one, or None on timeout, on :meth:`wake` (the reader's other
    conditions changed) or once closed. ``cond``: a condition shared with the writer's own state, so
    that a reader can wait for a new item or a change of that state at once (see :meth:`wait`).
    """

    def __init__(self, cond: threading.Condition | None = None) -> None:
        self._cond = cond if cond is not None else threading.Condition()
        self._item: T | None = None
        self._seq = 0
        self._closed = False
        #: per event loop with an async reader waiting: the event its readers wait on (replaced at each wake)
        self._events: dict[asyncio.AbstractEventLoop, asyncio.Event] = {}

    @property
    def seq(self) -> int:
        """The sequence number of the newest item (0 before the first)."""
        return self._seq

    def latest(self) -> T | None:
        """The newest item, or None before the first (never waits)."""
        return self._item

    def newest(self, after_seq: int = 0) -> tuple[int, T] | None:
        """``(seq, item)`` of the newest item if it is newer than ``after_seq``, else None (never waits)."""
        with self._cond:
            return (self._seq, self._item) if self._seq > after_seq else None

    def put(self, item: T) -> int:
        """Make ``item`` the newest and wake every reader; returns its sequence number."""
        with self._cond:
            self._seq += 1
            self._item = item
            self._cond.notify_all()
            self._wake_loops()
            return self._seq

    def wake(self) -> None:
        """Wake every waiting reader without a new item (it returns None and looks again at what it waits for)."""
        with self._cond:
            self._cond.notify_all()
            self._wake_loops()

    def close(self) -> None:
        """Wake every reader; from now on the waits return at once."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
            self._wake_loops()

    @property
    def closed(self) -> bool:
        return self._closed

    def wait(self, timeout: float | None) -> None:
        """Under the shared condition (``with cond``): wait until a ``put``, a ``wake``, a notification of the
        condition or ``timeout`` s; for a writer's reader whose wait also depends on the writer's state."""
        if not self._closed:
            self._cond.wait(timeout)

    def get_newest(self, after_seq: int = 0, timeout: float | None = None) -> tuple[int, T] | None:
        """``(seq, item)`` of the newest item once one is newer than ``after_seq``, waiting up to ``timeout``
        s in this thread; None on timeout, :meth:`wake` or close."""
        with self._cond:
            if self._seq <= after_seq and not self._closed:
                self._cond.wait(timeout)
            return (self._seq, self._item) if self._seq > after_seq else None

    async def wait_newest(self, after_seq: int = 0, timeout: float | None = None) -> tuple[int, T] | None:
        """As :meth:`get_newest`, waiting on the running event loop (one event per loop, whatever the number of
        readers; the writer's thread wakes it with one ``call_soon_threadsafe`` per item)."""
        loop = asyncio.get_running_loop()
        with self._cond:
            if self._seq > after_seq or self._closed:
                return (self._seq, self._item) if self._seq > after_seq else None
            event = self._events.get(loop)
            if event is None:
                event = self._events[loop] = asyncio.Event()
        try:
            await asyncio.wait_for(event.wait(), timeout)
        except TimeoutError:
            pass
        return self.newest(after_seq)

    def _wake_loops(self) -> None:
        """Under the condition: have each loop with a waiting reader set its event (on the loop's thread)."""
        for loop in list(self._events):
            try:
                loop.call_soon_threadsafe(self._set_event, loop)
            except RuntimeError:  # the loop closed: its readers are gone
                self._events.pop(loop, None)

    def _set_event(self, loop: asyncio.AbstractEventLoop) -> None:
        """On ``loop``: wake its readers; the next reader to wait makes a new event."""
        with self._cond:
            event = self._events.pop(loop, None)
        if event is not None:
            event.set()


class NewestSlot:
    """Bounded hand-off between two threads that keeps the newest items and drops the oldest.

    ``put`` never blocks; ``get`` blocks up to a timeout. ``dropped`` counts the
    items pushed out unread.
    """

    def __init__(self, capacity: int = 1) -> None:
        self._items: collections.deque = collections.deque()
        self._capacity = capacity
        self._cond = threading.Condition()
        self._closed = False
        self.dropped = 0

    def put(self, item: Any) -> int:
        """Add ``item``; returns how many old items were dropped to make room (0 or 1)."""
        with self._cond:
            dropped = 0
            while len(self._items) >= self._capacity:
                self._items.popleft()
                dropped += 1
            self._items.append(item)
            self.dropped += dropped
            self._cond.notify()
            return dropped

    def get(self, timeout: float) -> Any | None:
        """The oldest item still held, or None after ``timeout`` seconds or once closed."""
        with self._cond:
            if not self._items and not self._closed:
                self._cond.wait(timeout)
            return self._items.popleft() if self._items else None

    def close(self) -> None:
        """Wake any waiting ``get``; later gets return what is left, then None."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
