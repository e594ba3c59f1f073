"""ASGI middleware in front of every route: the bearer token and a bound on request bodies."""

from __future__ import annotations

import hmac
from typing import Any
from urllib.parse import parse_qs

from service.settings import MAX_TOKEN_LENGTH

#: Largest request body accepted (the settings JSON is a few hundred bytes).
MAX_BODY_BYTES = 16_384


class TokenGuard:
    """ASGI middleware: bearer token on every path but the ``public`` ones, and a bound on request bodies.

    The token comes from ``Authorization: Bearer TOKEN`` or ``?token=TOKEN`` (for
    ``<img>`` tags, which cannot send headers). A wrong or missing token gets a
    bare 401.
    """

    def __init__(self, app: Any, token: str | None, public: tuple[str, ...] = ("/healthz",)) -> None:
        self.app = app
        self.token = token.encode() if token else None
        self.public = frozenset(public)

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        headers = dict(scope.get("headers") or [])
        length = headers.get(b"content-length")
        if length is not None and (not length.isdigit() or int(length) > MAX_BODY_BYTES):
            return await plain(send, 413, b"request body too large\n")
        if self.token is not None and scope.get("path") not in self.public and not self._authorised(scope, headers):
            return await plain(send, 401, b"unauthorized\n", [(b"www-authenticate", b'Bearer realm="svelive"')])
        return await self.app(scope, receive, send)

    def _authorised(self, scope: dict, headers: dict[bytes, bytes]) -> bool:
        given = b""
        auth = headers.get(b"authorization", b"")
        if auth[:7].lower() == b"bearer ":
            given = auth[7:].strip()
        elif scope.get("query_string"):
            values = parse_qs(scope["query_string"].decode("latin-1")).get("token", [])
            given = values[0].encode("latin-1", "replace") if values else b""
        return 0 < len(given) <= MAX_TOKEN_LENGTH and hmac.compare_digest(given, self.token)


async def plain(send: Any, status: int, body: bytes, extra: list[tuple[bytes, bytes]] | None = None) -> None:
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"text/plain; charset=utf-8"),
                            (b"content-length", str(len(body)).encode()), *(extra or [])]})
    await send({"type": "http.response.body", "body": body})
