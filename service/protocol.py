"""uvicorn's h11 protocol with two bounds it lacks: time to send a request, and open connections.

Without them a client that opens connections and sends headers slowly (or never)
holds a file descriptor each for as long as it likes. uvicorn's keep-alive timeout
only starts after a response; ``limit_concurrency`` answers 503 but keeps the
connection.

At the bound, the connection that has waited longest for its request (slow headers, or idle
between keep-alive requests) is closed to make room, so connections that hold a slot without
asking for anything cannot lock out a health check or a viewer; only when every connection has a
request in progress (streams) is the new one refused.
"""

from __future__ import annotations

import asyncio
from typing import Any

import h11

from uvicorn.protocols.http.h11_impl import H11Protocol


class BoundedH11Protocol(H11Protocol):
    """An H11Protocol that closes a connection whose request (headers and body) is not complete within
    ``header_timeout`` seconds of connecting (or of the previous response), and keeps at most
    ``max_connections``: beyond it the one waiting longest for its request is closed, or, when every
    connection has a request in progress, the new one. Both are class attributes, set by :func:`bounded_protocol`."""

    header_timeout: float = 10.0
    max_connections: int = 512

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._header_deadline: asyncio.TimerHandle | None = None
        self._waiting_since: float | None = None
        if len(self.connections) > self.max_connections and not self._make_room():
            transport.abort()
            return
        self._arm_header_deadline()

    def _make_room(self) -> bool:
        """Close the connection that has waited longest for its request; False when none is waiting."""
        waiting = [c for c in self.connections if c is not self and getattr(c, "_waiting_since", None) is not None]
        if not waiting:
            return False
        oldest = min(waiting, key=lambda c: c._waiting_since)
        oldest._disarm_header_deadline()
        oldest.transport.abort()
        return True

    def _arm_header_deadline(self) -> None:
        self._disarm_header_deadline()
        self._waiting_scope = self.scope
        self._waiting_since = self.loop.time()
        self._header_deadline = self.loop.call_later(self.header_timeout, self._header_timeout_expired)

    def _disarm_header_deadline(self) -> None:
        self._waiting_since = None
        if getattr(self, "_header_deadline", None) is not None:
            self._header_deadline.cancel()
            self._header_deadline = None

    def _header_timeout_expired(self) -> None:
        self._header_deadline = None
        if not self.transport.is_closing():
            self.transport.close()

    def handle_events(self) -> None:
        super().handle_events()
        if (self._header_deadline is not None and self.scope is not self._waiting_scope
                and self.conn.their_state in (h11.DONE, h11.MUST_CLOSE, h11.CLOSED)):
            self._disarm_header_deadline()  # a new request arrived whole in time

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing():
            self._arm_header_deadline()

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm_header_deadline()
        super().connection_lost(exc)


def bounded_protocol(header_timeout: float, max_connections: int) -> type[BoundedH11Protocol]:
    """A protocol class for ``uvicorn.Config(http=...)`` with these bounds."""
    attributes: dict[str, Any] = {"header_timeout": float(header_timeout), "max_connections": int(max_connections)}
    return type("SveliveH11Protocol", (BoundedH11Protocol,), attributes)
