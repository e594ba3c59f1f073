"""uvicorn's h11 protocol with two bounds it lacks: time to send a request, and open connections.

Without them a client that opens connections and sends headers slowly (or never)
holds a file descriptor each for as long as it likes. uvicorn's keep-alive timeout
only starts after a response; ``limit_concurrency`` answers 503 but keeps the
connection.
"""

from __future__ import annotations

import asyncio
from typing import Any

import h11

from uvicorn.protocols.http.h11_impl import H11Protocol


class BoundedH11Protocol(H11Protocol):
    """An H11Protocol that closes a connection whose request (headers and body) is not complete within
    ``header_timeout`` seconds of connecting (or of the previous response), and refuses connections
    beyond ``max_connections``. Both are class attributes, set by :func:`bounded_protocol`."""

    header_timeout: float = 10.0
    max_connections: int = 512

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._header_deadline: asyncio.TimerHandle | None = None
        if len(self.connections) > self.max_connections:
            transport.abort()
            return
        self._arm_header_deadline()

    def _arm_header_deadline(self) -> None:
        self._disarm_header_deadline()
        self._waiting_scope = self.scope
        self._header_deadline = self.loop.call_later(self.header_timeout, self._header_timeout_expired)

    def _disarm_header_deadline(self) -> None:
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
