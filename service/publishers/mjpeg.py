"""MJPEG fan-out on the event loop.

The encoder thread puts every new JPEG into the pipeline's ``jpeg_port`` (a
:class:`service.pipeline.Newest`), which :class:`StreamHub` reads on the event loop.
Each stream client is an async generator that, after every part it sends, takes
the newest JPEG there is: a slow client skips frames (counted) and never builds a
queue; the socket's own buffer is the only backlog. A client that goes away ends
its generator, which frees its record.
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field
from typing import Any

from service.pipeline import EncodedFrame, LatencyWindow, Newest, RateMeter

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
    """The MJPEG clients of one camera, each waiting on the event loop for the newest JPEG of ``jpegs``."""

    def __init__(self, jpegs: Newest[EncodedFrame]) -> None:
        self._jpegs = jpegs
        self.clients: dict[int, StreamClient] = {}
        self._ids = itertools.count(1)
        self.streamed = RateMeter()
        self._max_sent_seq = 0
        self.sent_latency = LatencyWindow()
        self._part: tuple[EncodedFrame, bytes] | None = None  # the newest frame's part, shared by every client

    def part(self, item: EncodedFrame) -> bytes:
        """``item``'s multipart part (:func:`part_bytes`), made once for every client that sends it (the event
        loop is the only caller): a part is the JPEG's size, and ten clients would otherwise copy it ten times."""
        if self._part is None or self._part[0] is not item:
            self._part = (item, part_bytes(item))
        return self._part[1]

    async def wait_newer(self, seq: int, timeout: float) -> EncodedFrame | None:
        """The newest JPEG if its seq is above ``seq``, waiting up to ``timeout`` s for one; else None."""
        got = await self._jpegs.wait_newest(seq, timeout)
        return None if got is None else got[1]

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
