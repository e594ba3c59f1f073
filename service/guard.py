"""ASGI middleware in front of every route.

``SiteGuard`` (outermost) answers only requests meant for this server: a ``Host`` header
naming it (DNS rebinding), and, for requests that change state, no foreign ``Origin``
(cross-site requests) and a JSON body (no HTML form posts). ``TokenGuard`` checks the
bearer token, bounds request bodies as they stream in (chunked ones too), and answers
``HEAD`` on every ``GET`` route. Refusals are plain text, one line.
"""

from __future__ import annotations

import asyncio
import hmac
import ipaddress
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any
from urllib.parse import parse_qs, urlsplit

from service.settings import MAX_TOKEN_LENGTH

#: Largest request body accepted (the settings JSON is a few hundred bytes).
MAX_BODY_BYTES = 16_384
#: Methods that change state: their Origin and content type are checked.
UNSAFE_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})
LOOPBACK_NAMES = frozenset({"localhost", "127.0.0.1", "::1"})


def host_name(header: str) -> str:
    """The host of a ``Host`` header or an origin's netloc, without port or brackets, lower case:
    ``"[::1]:8000"`` -> ``"::1"``, ``"Camera.local.:80"`` -> ``"camera.local"``."""
    text = header.strip().lower()
    if text.startswith("["):
        return text[1:text.find("]")] if "]" in text else text[1:]
    if text.count(":") == 1:
        text = text.split(":", 1)[0]
    return text.rstrip(".")


def _ip(text: str) -> ipaddress.IPv4Address | ipaddress.IPv6Address | None:
    try:
        return ipaddress.ip_address(text)
    except ValueError:
        return None


@dataclass(frozen=True)
class HostPolicy:
    """Which ``Host`` headers the server answers (the defence against DNS rebinding).

    The rule, by the address the server is bound to:

    - any name in ``names`` (configured ``allowed_hosts``; ``"*"`` allows every host);
    - a loopback bind (127.0.0.1, ::1, localhost): ``localhost`` and loopback addresses;
    - a wildcard bind (0.0.0.0, ::): ``localhost`` and any IP address (people on the
      network reach it by its address), and any name at all when a token is set;
    - another address: that address, and any name at all when a token is set.

    A DNS rebinding attack needs a name the attacker controls: it is refused unless a
    token is set (which the attacker does not have). Ports are not compared: Docker's and
    proxies' port mappings change them, and a browser sends a port only to the server that
    listens on it.
    """

    bound: str
    names: frozenset[str] = frozenset()
    token: bool = False

    @classmethod
    def for_server(cls, host: str, allowed_hosts: Iterable[str] = (), token: bool = False) -> HostPolicy:
        return cls(host_name(host), frozenset(host_name(name) for name in allowed_hosts), token)

    @property
    def loopback(self) -> bool:
        ip = _ip(self.bound)
        return self.bound == "localhost" or (ip is not None and ip.is_loopback)

    @property
    def wildcard(self) -> bool:
        ip = _ip(self.bound)
        return ip is not None and ip.is_unspecified

    def allows(self, host: str) -> bool:
        """True when the ``Host`` header ``host`` names this server."""
        name = host_name(host)
        if "*" in self.names or name in self.names:
            return True
        ip = _ip(name)
        if self.loopback:
            return name == "localhost" or (ip is not None and ip.is_loopback)
        if ip is not None:
            return self.wildcard or ip == _ip(self.bound)
        if name == "localhost":
            return self.wildcard
        return self.token


def is_json(content_type: str) -> bool:
    """True for ``application/json`` and ``application/*+json`` (parameters such as charset ignored)."""
    kind = content_type.split(";", 1)[0].strip().lower()
    return kind == "application/json" or (kind.startswith("application/") and kind.endswith("+json"))


def origin_allowed(origin: str, host: str | None, cors_origins: Iterable[str]) -> bool:
    """True when a request with this ``Origin`` may change state: the server's own origin
    (same host and port as the ``Host`` header), or one of the CORS origins (``"*"``: any)."""
    allowed = {o.strip().rstrip("/").lower() for o in cors_origins}
    origin = origin.strip().rstrip("/").lower()
    if "*" in allowed or origin in allowed:
        return True
    if origin == "null" or host is None:
        return False
    netloc = urlsplit(origin).netloc
    return bool(netloc) and netloc == host.strip().lower()


class SiteGuard:
    """ASGI middleware: refuses requests that are not meant for this server (see the module docstring).

    403 for a ``Host`` this server does not answer to, or a state-changing request from a
    foreign ``Origin``; 415 for a state-changing request with a body that is not JSON.
    """

    def __init__(self, app: Any, hosts: HostPolicy, cors_origins: Iterable[str] = ()) -> None:
        self.app = app
        self.hosts = hosts
        self.cors_origins = tuple(cors_origins)

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        headers = dict(scope.get("headers") or [])
        raw_host = headers.get(b"host")
        host = None if raw_host is None else raw_host.decode("latin-1")
        if host is not None and not self.hosts.allows(host):
            return await plain(send, 403, f"host {host_name(host)!r} is not a name of this server; start it with "
                               "--allowed-host NAME to allow it\n".encode("latin-1", "replace"))
        if scope.get("method", "GET").upper() in UNSAFE_METHODS:
            origin = headers.get(b"origin")
            if origin is not None and not origin_allowed(origin.decode("latin-1"), host, self.cors_origins):
                return await plain(send, 403, f"cross-site request refused: origin {origin.decode('latin-1')!r} is "
                                   "neither this server nor a configured CORS origin\n".encode("latin-1", "replace"))
            content_type = headers.get(b"content-type")
            if content_type is not None and not is_json(content_type.decode("latin-1")):
                return await plain(send, 415, b"the request body must be JSON (Content-Type: application/json)\n")
            if content_type is None and has_body(headers):
                return await plain(send, 415, b"a request body needs Content-Type: application/json\n")
        return await self.app(scope, receive, send)


def has_body(headers: dict[bytes, bytes]) -> bool:
    """True when the request announces a body (a non-zero Content-Length, or any Transfer-Encoding)."""
    length = headers.get(b"content-length", b"0").strip()
    return b"transfer-encoding" in headers or length not in (b"", b"0")


class BodyTooLarge(Exception):
    """The request body went past MAX_BODY_BYTES."""


class TokenGuard:
    """ASGI middleware: bearer token on every path but the ``public`` ones, a bound on request
    bodies, and ``HEAD`` for every ``GET`` route.

    The token comes from ``Authorization: Bearer TOKEN`` or ``?token=TOKEN`` (for
    ``<img>`` tags, which cannot send headers). A wrong or missing token gets a
    bare 401 (and the connection closed when a body follows, which stays unread). A body is read (up to ``max_body`` bytes) before the route runs, whatever
    its framing: a ``Content-Length`` above the bound, or a chunked body that grows past
    it, gets 413 and the connection is closed, so the rest is never read.
    """

    def __init__(self, app: Any, token: str | None, public: tuple[str, ...] = ("/healthz",),
                 max_body: int = MAX_BODY_BYTES) -> None:
        self.app = app
        self.token = token.encode() if token else None
        self.public = frozenset(public)
        self.max_body = max_body

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        headers = dict(scope.get("headers") or [])
        length = headers.get(b"content-length")
        if length is not None and (not length.isdigit() or int(length) > self.max_body):
            return await plain(send, 413, b"request body too large\n", close=True)
        if self.token is not None and scope.get("path") not in self.public and not self._authorised(scope, headers):
            # with a body, the connection is closed after the 401: else the server read the body to its end
            # (gigabytes of a chunked one) to keep the connection for the next request
            return await plain(send, 401, b"unauthorized\n", [(b"www-authenticate", b'Bearer realm="svelive"')],
                               close=has_body(headers))
        if has_body(headers):
            try:
                receive = await self._bounded_body(receive)
            except BodyTooLarge:
                return await plain(send, 413, b"request body too large\n", close=True)
        if scope.get("method") == "HEAD":
            return await self._head(scope, receive, send)
        return await self.app(scope, receive, send)

    async def _bounded_body(self, receive: Any) -> Any:
        """Read the whole body (at most ``max_body`` bytes, else BodyTooLarge); returns a
        ``receive`` that hands it to the app in one message, then passes on to ``receive``."""
        chunks: list[bytes] = []
        size = 0
        while True:
            message = await receive()
            if message["type"] != "http.request":  # the client went away: let the app see it
                first = message
                break
            chunks.append(message.get("body", b""))
            size += len(chunks[-1])
            if size > self.max_body:
                raise BodyTooLarge
            if not message.get("more_body", False):
                first = {"type": "http.request", "body": b"".join(chunks), "more_body": False}
                break
        pending = [first]

        async def replay() -> dict:
            return pending.pop() if pending else await receive()

        return replay

    async def _head(self, scope: dict, receive: Any, send: Any) -> None:
        """Run the GET route and send only its status and headers; a stream's generator is
        cancelled once they are out."""
        done = asyncio.Event()

        async def send_headers(message: dict) -> None:
            if done.is_set() or message["type"] != "http.response.start":
                return
            await send(message)
            await send({"type": "http.response.body", "body": b"", "more_body": False})
            done.set()

        task = asyncio.ensure_future(self.app({**scope, "method": "GET"}, receive, send_headers))
        waiter = asyncio.ensure_future(done.wait())
        try:
            await asyncio.wait({task, waiter}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            waiter.cancel()
            if not task.done():
                task.cancel()
                await asyncio.wait({task})
        if not task.cancelled() and task.exception() is not None:
            raise task.exception()  # type: ignore[misc]

    def _authorised(self, scope: dict, headers: dict[bytes, bytes]) -> bool:
        given = b""
        auth = headers.get(b"authorization", b"")
        if auth[:7].lower() == b"bearer ":
            given = auth[7:].strip()
        elif scope.get("query_string"):
            values = parse_qs(scope["query_string"].decode("latin-1")).get("token", [])
            given = values[0].encode("latin-1", "replace") if values else b""
        return 0 < len(given) <= MAX_TOKEN_LENGTH and hmac.compare_digest(given, self.token)


async def plain(send: Any, status: int, body: bytes, extra: list[tuple[bytes, bytes]] | None = None,
                close: bool = False) -> None:
    """A plain-text answer; ``close`` ends the connection after it (an unread body stays unread)."""
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"text/plain; charset=utf-8"),
                            (b"content-length", str(len(body)).encode()), *(extra or []),
                            *([(b"connection", b"close")] if close else [])]})
    await send({"type": "http.response.body", "body": body})
