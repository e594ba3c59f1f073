"""MJPEG fan-out on the event loop.

The encoder thread hands every new JPEG to :class:`StreamHub`, which lives on
the event loop. Each stream client is an async generator that, after every part
it sends, takes the newest JPEG there is: a slow client skips frames (counted)
and never builds a queue; the socket's own buffer is the only backlog. A client
that goes away ends its generator, which frees its record.
"""

from __future__ import annotations

import asyncio
import itertools
import time
from dataclasses import dataclass, field
from typing import Any

from service.pipeline import EncodedFrame, LatencyWindow, RateMeter

BOUNDARY = "svelive-frame"


@dataclass
class StreamClient:
    """One connected MJPEG client."""

    id: int
    remote: str
    connected_ns: int = field(default_factory=time.monotonic_ns)
    sent: int = 0
    skipped: int = 0
    meter: RateMeter = field(default_factory=RateMeter)

    def summary(self) -> dict[str, Any]:
        return {"id": self.id, "remote": self.remote, "sent": self.sent, "skipped": self.skipped,
                "fps": round(self.meter.rate(), 2),
                "connected_s": round((time.monotonic_ns() - self.connected_ns) / 1e9, 1)}


class StreamHub:
    """The newest preview JPEG on the event loop, and the clients waiting for it."""

    def __init__(self, loop: asyncio.AbstractEventLoop) -> None:
        self._loop = loop
        self.latest: EncodedFrame | None = None
        self._event = asyncio.Event()
        self.clients: dict[int, StreamClient] = {}
        self._ids = itertools.count(1)
        self.streamed = RateMeter()
        self._max_sent_seq = 0
        self.sent_latency = LatencyWindow()

    def on_frame(self, item: EncodedFrame) -> None:
        """Called from the encoder thread."""
        try:
            self._loop.call_soon_threadsafe(self._publish, item)
        except RuntimeError:  # the loop is closed: the server is shutting down
            pass

    def _publish(self, item: EncodedFrame) -> None:
        self.latest = item
        event, self._event = self._event, asyncio.Event()
        event.set()

    async def wait_newer(self, seq: int, timeout: float) -> EncodedFrame | None:
        """The newest JPEG if its seq is above ``seq``, waiting up to ``timeout`` s for one; else None."""
        item = self.latest
        if item is not None and item.seq > seq:
            return item
        try:
            await asyncio.wait_for(self._event.wait(), timeout)
        except TimeoutError:
            return None
        item = self.latest
        return item if item is not None and item.seq > seq else None

    def register(self, remote: str) -> StreamClient:
        client = StreamClient(next(self._ids), remote)
        self.clients[client.id] = client
        return client

    def sent(self, client: StreamClient, item: EncodedFrame, previous_seq: int) -> None:
        now = time.monotonic_ns()
        client.sent += 1
        if previous_seq:
            client.skipped += item.seq - previous_seq - 1
        client.meter.tick(now)
        if item.seq > self._max_sent_seq:
            self._max_sent_seq = item.seq
            self.streamed.tick(now)
        if item.signal:
            self.sent_latency.add((now - item.host_time_ns) / 1e6)

    def state(self) -> dict[str, Any]:
        """The MJPEG publisher's part of /api/state."""
        clients = list(self.clients.values())
        return {"streamed": self.streamed.count, "streamed_fps": round(self.streamed.rate(), 2), "arrival_to_sent": self.sent_latency.summary(),
                "clients": len(clients), "client_list": [c.summary() for c in clients[:100]],
                "client_skipped": sum(c.skipped for c in clients)}


def part_bytes(item: EncodedFrame) -> bytes:
    """One multipart part: boundary, headers (type, length, timestamp, frame id), the JPEG, CRLF."""
    headers = [f"--{BOUNDARY}", "Content-Type: image/jpeg", f"Content-Length: {len(item.jpeg)}",
               f"X-Timestamp: {item.wall_time:.6f}", f"X-Signal: {'live' if item.signal else 'none'}"]
    if item.frame_id is not None:
        headers.append(f"X-Frame-Id: {item.frame_id}")
    return ("\r\n".join(headers) + "\r\n\r\n").encode() + item.jpeg + b"\r\n"
