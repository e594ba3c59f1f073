"""The HTTP API fuzzed from its own OpenAPI schema (benchmarks/fuzz_api.py, fewer cases): never a 5xx.

A real uvicorn server on 127.0.0.1 over the demo source; hypothesis draws the requests
(valid and hostile bodies, query values, content types, origins, hosts) and shrinks a
failing one to a minimal example.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

pytest.importorskip("hypothesis")

CASES = 200


def load_fuzz():
    path = Path(__file__).resolve().parents[1] / "benchmarks" / "fuzz_api.py"
    spec = importlib.util.spec_from_file_location("fuzz_api", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("token", [None, "fuzz-token"])
def test_fuzzed_requests_never_get_a_5xx_or_a_traceback(token):
    fuzz_api = load_fuzz()
    with fuzz_api.FuzzServer(token) as server:
        result = fuzz_api.fuzz(server, CASES // 2, seed=1 if token else 0, token=token)
    assert result["cases"] == CASES // 2
    assert result["server_errors_5xx"] == 0, result["examples_5xx"]
    assert result["tracebacks"] == 0, result["examples_tracebacks"]
    # the fuzz reached the routes: refusals and validation alone would not show every kind of answer
    assert {"200", "403", "422"} <= set(result["statuses"]), result["statuses"]


def test_the_operations_cover_every_route_and_head():
    fuzz_api = load_fuzz()
    from service.app import create_app
    from service.pipeline import Pipeline, PipelineConfig
    from service.settings import ServerSettings

    app = create_app(Pipeline(PipelineConfig(source="demo")), ServerSettings())
    ops = {(op.method, op.path) for op in fuzz_api.operations(app.openapi())}
    for method, path in (("PUT", "/api/settings"), ("POST", "/api/calibrate/response"), ("HEAD", "/healthz"),
                         ("GET", "/stream.mjpg"), ("DELETE", "/cam/main/api/calibrate/response")):
        assert (method, path) in ops
    body = next(op.body for op in fuzz_api.operations(app.openapi()) if op.method == "PUT")
    assert "$ref" not in repr(body) and "tone" in repr(body)
