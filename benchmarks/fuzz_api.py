"""Fuzz the HTTP API from its own OpenAPI schema: counts of answers by status class, 5xx and tracebacks.

    python benchmarks/fuzz_api.py [--cases 2000] [--seed 0] [--token]

Runs ``svelive serve``'s app (real uvicorn, in a thread of this process, on a free
127.0.0.1 port) over the demo source at 224x192, 10 fps, then sends ``--cases``
requests, each drawn by hypothesis from ``app.openapi()`` (the schema exists even
though the server does not publish it):

- an operation (method and path, including ``/cam/main/...`` and HEAD on GET routes);
- its query parameters and JSON body drawn from the schema (``from_schema``: the JSON
  Schema subset FastAPI writes; hypothesis-jsonschema 0.23.1 fails on hypothesis 6.170),
  then, half of the time, made hostile: a field replaced by NaN, Infinity, 1e999, a
  lone surrogate, a huge or negative number, a wrong type, deep nesting, or the body
  replaced by arbitrary JSON or raw bytes (invalid UTF-8, truncated JSON);
- headers drawn from JSON / form / text / no content type, the own, a foreign or a
  ``null`` Origin, and the own or a foreign Host (DNS rebinding).

The MJPEG stream is read up to its first part. A calibration request (POST
/api/calibrate/response) costs about a second of CPU, so those are 1 in 20.

It prints one JSON line: cases, answers by status, the number of 5xx answers and of
tracebacks the server logged (uvicorn's "Exception in ASGI application"), and the
first examples of each. Needs hypothesis (``pip install hypothesis``).
"""

from __future__ import annotations

import argparse
import collections
import copy
import json
import logging
import os
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import quote

# Run as a script, this file's directory comes first on sys.path; the repository root must be there.
_HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:] = [p for p in sys.path if os.path.abspath(p or ".") != _HERE]
sys.path.insert(0, os.path.dirname(_HERE))

from svelive.core.errors import SveliveError  # noqa: E402

try:
    import httpx
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st
except ImportError as exc:  # pragma: no cover - the message names what to install
    raise SystemExit(str(SveliveError(f"the API fuzz needs {exc.name}: pip install hypothesis")))

#: Values that JSON encoders and validators get wrong; ``1e999`` is written into the text as is.
HOSTILE_VALUES = [float("nan"), float("inf"), float("-inf"), "1e999", "-1e999", "\ud800", "\udfff", "x\ud83d",
                  2**64, -2**63, 1e308, -1e-320, True, None, "", "a" * 20_000, [], {}, [[[[[]]]]], "NaN",
                  "\u0000", "\u202e", "\U0001f600"]
CONTENT_TYPES = ["application/json", "application/json", "application/json", None,
                 "application/x-www-form-urlencoded", "text/plain", "multipart/form-data; boundary=x",
                 "application/json; charset=latin-1", "application/merge-patch+json"]


def inline_refs(node: Any, components: dict[str, Any], depth: int = 0) -> Any:
    """The schema ``node`` with every ``#/components/schemas/NAME`` reference replaced by its schema."""
    if depth > 20:
        return {}
    if isinstance(node, dict):
        ref = node.get("$ref")
        if isinstance(ref, str) and ref.startswith("#/components/schemas/"):
            return inline_refs(components[ref.rsplit("/", 1)[1]], components, depth + 1)
        return {k: inline_refs(v, components, depth + 1) for k, v in node.items()}
    if isinstance(node, list):
        return [inline_refs(v, components, depth + 1) for v in node]
    return node


def from_schema(schema: dict[str, Any]) -> st.SearchStrategy:
    """Values valid under ``schema``, a JSON Schema of the kind FastAPI writes for pydantic models
    (``anyOf``, ``type`` null/boolean/integer/number/string/array/object, bounds, ``maxLength``,
    ``properties``); anything else: any JSON value."""
    if "anyOf" in schema:
        return st.one_of([from_schema(option) for option in schema["anyOf"]])
    kind = schema.get("type")
    if kind == "null":
        return st.none()
    if kind == "boolean":
        return st.booleans()
    if kind in ("integer", "number"):
        low, high = schema.get("minimum", schema.get("exclusiveMinimum")), schema.get("maximum")
        if kind == "integer":
            return st.integers(None if low is None else int(low), None if high is None else int(high))
        return st.floats(low, high, allow_nan=False, allow_infinity=False,
                         exclude_min="exclusiveMinimum" in schema)
    if kind == "string":
        return st.text(max_size=min(schema.get("maxLength", 32), 32))
    if kind == "array":
        return st.lists(from_schema(schema.get("items", {})), max_size=10)
    if kind == "object":
        props = {name: from_schema(sub) for name, sub in schema.get("properties", {}).items()}
        return st.fixed_dictionaries({}, optional=props)
    return ANY_JSON


@dataclass(frozen=True)
class Operation:
    """One method on one path of the schema, with the schemas of its query and its JSON body."""

    method: str
    path: str
    query: dict[str, Any] = field(default_factory=dict)
    body: dict[str, Any] | None = None


def operations(spec: dict[str, Any]) -> list[Operation]:
    """Every operation of an OpenAPI document, plus HEAD for every GET."""
    components = spec.get("components", {}).get("schemas", {})
    ops = []
    for path, items in sorted(spec["paths"].items()):
        for method, op in sorted(items.items()):
            query = {p["name"]: inline_refs(p.get("schema", {}), components)
                     for p in op.get("parameters", []) if p.get("in") == "query"}
            body = op.get("requestBody", {}).get("content", {}).get("application/json", {}).get("schema")
            body = None if body is None else inline_refs(body, components)
            ops.append(Operation(method.upper(), path, query, body))
            if method.upper() == "GET":
                ops.append(Operation("HEAD", path, query, None))
    return ops


def json_text(value: Any) -> str:
    """JSON text of ``value`` the way a careless client writes it: NaN and Infinity as such,
    lone surrogates as \\u escapes, and the string "1e999" as the bare number."""
    text = json.dumps(value, allow_nan=True)
    return text.replace('"1e999"', "1e999").replace('"-1e999"', "-1e999")


def hostile(draw: Any, value: Any) -> Any:
    """``value`` with one leaf (or the whole) replaced by a hostile value."""
    if isinstance(value, dict) and value and draw(st.booleans()):
        key = draw(st.sampled_from(sorted(value)))
        out = dict(value)
        out[key] = hostile(draw, value[key])
        return out
    if isinstance(value, list) and value and draw(st.booleans()):
        index = draw(st.integers(0, len(value) - 1))
        out = list(value)
        out[index] = hostile(draw, value[index])
        return out
    return copy.deepcopy(draw(st.sampled_from(HOSTILE_VALUES)))


ANY_JSON = st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
                        lambda kids: st.lists(kids, max_size=4) | st.dictionaries(st.text(max_size=10), kids, max_size=4),
                        max_leaves=12)


@st.composite
def requests(draw: Any, ops: list[Operation], host: str, calibrate_one_in: int = 20) -> dict[str, Any]:
    """One request: method, path, query, headers and body bytes (see the module docstring)."""
    calibrating = [op for op in ops if op.method == "POST" and "calibrate" in op.path]
    others = [op for op in ops if op not in calibrating]
    op = draw(st.sampled_from(calibrating)) if calibrating and draw(st.integers(1, calibrate_one_in)) == calibrate_one_in \
        else draw(st.sampled_from(others))
    query: dict[str, str] = {}
    for name, schema in op.query.items():
        if draw(st.booleans()):
            value = draw(from_schema(schema)) if draw(st.booleans()) else draw(st.sampled_from(HOSTILE_VALUES))
            query[name] = value if isinstance(value, str) else json_text(value)
    body: bytes | None = None
    if op.body is not None and draw(st.integers(0, 9)) > 0:
        kind = draw(st.sampled_from(["schema", "schema", "hostile", "hostile", "any", "bytes"]))
        if kind == "bytes":
            body = draw(st.binary(max_size=64))
        else:
            value = draw(from_schema(op.body)) if kind != "any" else draw(ANY_JSON)
            if kind == "hostile":
                value = hostile(draw, value)
            body = json_text(value).encode("utf-8", "surrogatepass")
            if draw(st.integers(0, 19)) == 0:
                body = body[:max(1, len(body) // 2)]  # truncated
    headers = {}
    content_type = draw(st.sampled_from(CONTENT_TYPES))
    if body is not None and content_type is not None:
        headers["content-type"] = content_type
    origin = draw(st.sampled_from([None, None, f"http://{host}", "http://attacker.example", "null"]))
    if origin is not None:
        headers["origin"] = origin
    headers["host"] = draw(st.sampled_from([host, host, host, "localhost", "attacker.example", "[::1]"]))
    return {"method": op.method, "path": op.path, "query": query, "headers": headers, "body": body}


class TracebackCounter(logging.Handler):
    """Counts log records that carry an exception (uvicorn logs a failing request that way)."""

    def __init__(self) -> None:
        super().__init__(logging.ERROR)
        self.records: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        if record.exc_info:
            self.records.append(f"{record.getMessage()}: {record.exc_info[1]!r}"[:300])


class FuzzServer:
    """``svelive serve``'s app over the demo source on a free 127.0.0.1 port, in a thread."""

    def __init__(self, token: str | None = None) -> None:
        import uvicorn

        from service.app import create_app, listen_socket
        from service.pipeline import Pipeline, PipelineConfig
        from service.settings import ServerSettings

        config = PipelineConfig(source="demo", source_options={"width": 224, "height": 192, "fps": 10.0},
                                temporal=False, workers=1)
        self.settings = ServerSettings(port=0, token=token)
        self.sock = listen_socket(self.settings)
        self.port = self.sock.getsockname()[1]
        self.url = f"http://127.0.0.1:{self.port}"
        self.app = create_app(Pipeline(config), self.settings)
        self.server = uvicorn.Server(uvicorn.Config(self.app, log_level="warning", timeout_graceful_shutdown=1))
        self.thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.sock]}, daemon=True)
        self.tracebacks = TracebackCounter()

    def __enter__(self) -> FuzzServer:
        for name in ("uvicorn.error", "uvicorn", "fastapi", "starlette"):
            logging.getLogger(name).addHandler(self.tracebacks)
        self.thread.start()
        deadline = time.monotonic() + 30
        while not self.server.started:
            if time.monotonic() > deadline or not self.thread.is_alive():
                raise RuntimeError("uvicorn did not start")
            time.sleep(0.02)
        deadline = time.monotonic() + 120  # the first frame may compile the kernels
        while self.app.state.pipeline.latest() is None:  # before it, snapshots answer 503 by design
            if time.monotonic() > deadline:
                raise RuntimeError("no frame reconstructed within 120 s")
            time.sleep(0.1)
        return self

    def __exit__(self, *exc: object) -> None:
        getattr(self.app.state, "shutdown_streams", lambda: None)()
        self.server.should_exit = True
        self.thread.join(10)
        self.sock.close()
        for name in ("uvicorn.error", "uvicorn", "fastapi", "starlette"):
            logging.getLogger(name).removeHandler(self.tracebacks)


def send(client: httpx.Client, base: str, request: dict[str, Any]) -> int:
    """Send one drawn request; returns the status (the stream is read up to its first part)."""
    # percent-encoded by hand: a lone surrogate goes out as the (invalid) UTF-8 bytes it stands for
    query = "&".join(f"{quote(k)}={quote(v.encode('utf-8', 'surrogatepass'))}" for k, v in request["query"].items())
    url = base + request["path"] + (f"?{query}" if query else "")
    with client.stream(request["method"], url, headers=request["headers"], content=request["body"]) as response:
        if response.headers.get("content-type", "").startswith("multipart/"):
            for _ in response.iter_raw():  # the first chunk: the stream works
                break
        else:
            response.read()
        return response.status_code


def fuzz(server: FuzzServer, cases: int, seed: int = 0, token: str | None = None) -> dict[str, Any]:
    """Send ``cases`` drawn requests to ``server``; returns the counts (see the module docstring)."""
    from hypothesis import seed as hypothesis_seed

    ops = operations(server.app.openapi())
    statuses: collections.Counter = collections.Counter()
    failures: list[dict[str, Any]] = []
    auth = {"authorization": f"Bearer {token}"} if token else {}
    client = httpx.Client(timeout=30, headers=auth)
    host = f"127.0.0.1:{server.port}"

    @hypothesis_seed(seed)
    @settings(max_examples=cases, deadline=None, database=None, derandomize=False,
              suppress_health_check=list(HealthCheck))
    @given(requests(ops, host))
    def one(request: dict[str, Any]) -> None:
        status = send(client, server.url, request)
        statuses[status] += 1
        if status >= 500 and len(failures) < 5:
            failures.append({k: (v if not isinstance(v, bytes) else v[:200].decode("latin-1"))
                             for k, v in request.items()} | {"status": status})

    try:
        one()
    finally:
        client.close()
    return {"cases": sum(statuses.values()), "operations": len(ops),
            "statuses": {str(k): v for k, v in sorted(statuses.items())},
            "server_errors_5xx": sum(v for k, v in statuses.items() if k >= 500),
            "tracebacks": len(server.tracebacks.records), "examples_5xx": failures,
            "examples_tracebacks": server.tracebacks.records[:5]}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=2000, help="requests to send (default 2000)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--token", action="store_true", help="run the server with a token (and send it)")
    args = parser.parse_args()
    token = "fuzz-token" if args.token else None
    t0 = time.monotonic()
    with FuzzServer(token) as server:
        result = fuzz(server, args.cases, args.seed, token)
    result["seconds"] = round(time.monotonic() - t0, 1)
    print(json.dumps(result))
    return 1 if result["server_errors_5xx"] or result["tracebacks"] else 0


if __name__ == "__main__":
    sys.exit(main())
