"""The HTTP service against hostile or unusual requests: bodies, hosts, origins, HEAD, bad JSON.

Every test talks to a real uvicorn server on 127.0.0.1 (tests.test_service_helpers.ServerThread).
"""

from __future__ import annotations

import json
import socket
import time

import httpx
import pytest

from service.guard import MAX_BODY_BYTES

from tests.test_service_helpers import ServerThread, make_camera


@pytest.fixture(scope="module")
def server():
    with ServerThread(make_camera(fps=10.0, n=2), server={"cors_origins": ("http://viewer.example:9000",),
                                                          "allowed_hosts": ("camera.lan",)}) as srv:
        yield srv


# ----- request bodies -------------------------------------------------------
def send_chunked(port: int, path: str, total: int, headers: str = "", chunk: int = 65_536) -> tuple[int, bytes]:
    """PUT a chunked body of up to ``total`` bytes; returns (bytes the server let us send, its answer).

    Stops sending when the server closes the connection or stops reading for 3 s."""
    sock = socket.create_connection(("127.0.0.1", port), timeout=3)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 65_536)
    sent = 0
    try:
        sock.sendall(f"PUT {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n{headers}"
                     "Transfer-Encoding: chunked\r\n\r\n".encode())
        piece = f"{chunk:x}\r\n".encode() + b" " * chunk + b"\r\n"
        while sent < total:  # bounded: at most total / chunk sends
            sock.sendall(piece)
            sent += chunk
        sock.sendall(b"0\r\n\r\n")
    except (BrokenPipeError, ConnectionResetError, TimeoutError, socket.timeout):
        pass
    answer = b""
    try:
        sock.settimeout(3)
        while len(answer) < 4096:
            data = sock.recv(4096)
            if not data:
                break
            answer += data
    except (ConnectionResetError, TimeoutError, socket.timeout):
        pass
    finally:
        sock.close()
    return sent, answer


@pytest.mark.parametrize("token", [None, "tok3n"])
def test_a_chunked_body_past_the_bound_is_refused_while_it_streams(token):
    with ServerThread(make_camera(fps=5.0, n=2), token=token) as srv:
        srv.wait_for(lambda s: s["frames"]["reconstructed"] > 0,  # /healthz ready from then on
                     headers={"Authorization": f"Bearer {token}"} if token else {})
        auth = f"Authorization: Bearer {token}\r\n" if token else ""
        total = 64 * 2**20
        sent, answer = send_chunked(srv.port, "/api/settings", total, auth)
        # the server stops reading after 16 KiB: what went out is what the socket buffers held
        assert sent < 16 * 2**20, sent
        assert answer == b"" or answer.startswith(b"HTTP/1.1 413"), answer[:100]
        # a small chunked body still works
        sent, answer = send_chunked(srv.port, "/api/settings", 1, auth, chunk=2)
        assert answer.startswith(b"HTTP/1.1 422"), answer[:200]  # two spaces are not JSON: validated, not refused
        assert httpx.get(srv.url + "/healthz", timeout=5).status_code == 200  # the server is fine


def test_a_body_with_a_large_content_length_is_refused_before_it_is_read(server):
    r = httpx.put(server.url + "/api/settings", content=b"{" + b" " * MAX_BODY_BYTES + b"}",
                  headers={"content-type": "application/json"}, timeout=5)
    assert r.status_code == 413 and r.text == "request body too large\n"
    r = httpx.put(server.url + "/api/settings", content=b'{"jpeg_quality": 80}' + b" " * 10_000,
                  headers={"content-type": "application/json"}, timeout=5)
    assert r.status_code == 200


# ----- bad JSON: always a 4xx with one line ------------------------------------------
BAD_VALUES = ["NaN", "Infinity", "-Infinity", "1e999", "-1e999", '"\\ud800"', '"\\udfff x"', '["\\ud800"]',
              "[NaN, 1, 1]", "[1e999, 1, 1]", '{"\\ud800": NaN}']
SETTINGS_FIELDS = ["method", "jpeg_quality", "white_balance", "colour_matrix", "output_space", "tone", "\\ud800"]
TONE_FIELDS = ["exposure_ev", "key", "white_percentile", "adapt_s"]


def bad_bodies() -> list[tuple[str, str]]:
    bodies = [("/api/settings", f'{{"{name}": {value}}}') for name in SETTINGS_FIELDS for value in BAD_VALUES]
    bodies += [("/api/settings", f'{{"tone": {{"{name}": {value}}}}}') for name in TONE_FIELDS for value in BAD_VALUES]
    bodies += [("/api/calibrate/response", f'{{"{name}": {value}}}') for name in ("max_degree", "apply", "\\ud800")
               for value in BAD_VALUES]
    bodies += [(path, value) for path in ("/api/settings", "/api/calibrate/response") for value in BAD_VALUES]
    bodies += [("/api/settings", '{"tone": {"exposure_ev": -NaN}}'), ("/api/settings", '{"tone": {"key": 0.2,}}')]
    return bodies


def test_non_finite_numbers_and_lone_surrogates_get_a_one_line_4xx(server):
    before = server.pipeline.settings()
    failures = []
    for path, body in bad_bodies():
        method = "PUT" if path == "/api/settings" else "POST"
        r = httpx.request(method, server.url + path, content=body.encode("utf-8", "surrogatepass"),
                          headers={"content-type": "application/json"}, timeout=30)
        detail = r.json().get("detail") if r.headers.get("content-type") == "application/json" else None
        if r.status_code == 200 and path == "/api/calibrate/response":
            continue  # a body the calibration accepts (e.g. {"apply": ...} is not among these)
        if not (400 <= r.status_code < 500 and isinstance(detail, str) and "\n" not in detail and detail):
            failures.append((body, r.status_code, r.text[:120]))
    assert failures == [], '\n'.join(map(repr, failures))
    assert server.pipeline.settings() == before  # nothing half-applied


def test_an_infinite_or_nan_tone_value_is_named(server):
    r = httpx.put(server.url + "/api/settings", content=b'{"tone": {"key": NaN}}',
                  headers={"content-type": "application/json"}, timeout=5)
    assert r.status_code == 422 and r.json()["detail"].startswith("tone.key: ") and "finite" in r.json()["detail"]
    r = httpx.put(server.url + "/api/settings", content=b'{"tone": {"key": 0.2,}}',
                  headers={"content-type": "application/json"}, timeout=5)
    assert r.status_code == 422 and r.json()["detail"].startswith("the body is not valid JSON at character ")


# ----- hosts, origins, content types -------------------------------------------------
def test_a_foreign_host_header_is_refused(server):
    for path in ("/snapshot.jpg", "/api/state", "/", "/stream.mjpg", "/healthz"):
        r = httpx.get(server.url + path, headers={"Host": "attacker.example"}, timeout=5)
        assert r.status_code == 403 and "attacker.example" in r.text and r.text.count("\n") == 1, (path, r.text)
    r = httpx.put(server.url + "/api/settings", json={"jpeg_quality": 33}, headers={"Host": "attacker.example:80"},
                  timeout=5)
    assert r.status_code == 403 and server.pipeline.settings()["jpeg_quality"] != 33
    for host in ("localhost", f"localhost:{server.port}", f"127.0.0.1:{server.port}", f"[::1]:{server.port}",
                 "camera.lan", "CAMERA.LAN:8080"):
        assert httpx.get(server.url + "/api/state", headers={"Host": host}, timeout=5).status_code == 200, host


def test_a_cross_site_write_is_refused(server):
    url = server.url + "/api/settings"
    for origin in ("http://attacker.example", "null", f"http://127.0.0.1:{server.port + 1}",
                   f"http://localhost:{server.port}"):  # another origin (different host text) than the page's
        r = httpx.put(url, json={"jpeg_quality": 33}, headers={"Origin": origin}, timeout=5)
        assert r.status_code == 403 and "cross-site" in r.text, (origin, r.text)
    r = httpx.post(server.url + "/api/calibrate/response", content=b"max_degree=3",
                   headers={"Origin": "http://attacker.example",
                            "Content-Type": "application/x-www-form-urlencoded"}, timeout=5)
    assert r.status_code == 403
    assert server.pipeline.settings()["jpeg_quality"] != 33
    # the page's own origin, a configured CORS origin, and tools that send no Origin
    for headers in ({"Origin": server.url}, {"Origin": "http://viewer.example:9000"}, {}):
        assert httpx.put(url, json={"jpeg_quality": 70}, headers=headers, timeout=5).status_code == 200, headers
    # reading is not a write: a foreign origin may GET (CORS keeps its script from reading the answer)
    assert httpx.get(server.url + "/api/state", headers={"Origin": "http://attacker.example"}, timeout=5).status_code == 200


def test_a_form_post_or_text_body_is_refused(server):
    for content_type in ("application/x-www-form-urlencoded", "multipart/form-data; boundary=x", "text/plain"):
        r = httpx.post(server.url + "/api/calibrate/response", content=b"max_degree=3",
                       headers={"Content-Type": content_type}, timeout=5)
        assert r.status_code == 415 and "JSON" in r.text, (content_type, r.status_code, r.text)
        r = httpx.put(server.url + "/api/settings", content=b'{"jpeg_quality": 33}',
                      headers={"Content-Type": content_type}, timeout=5)
        assert r.status_code == 415
    r = httpx.put(server.url + "/api/settings", content=b'{"jpeg_quality": 33}', headers={"Content-Type": ""},
                  timeout=5)
    assert r.status_code == 415
    assert server.pipeline.settings()["jpeg_quality"] != 33
    r = httpx.put(server.url + "/api/settings", content=b'{"jpeg_quality": 71}',
                  headers={"Content-Type": "application/json; charset=utf-8"}, timeout=5)
    assert r.status_code == 200
    assert httpx.delete(server.url + "/api/calibrate/response", timeout=5).status_code == 200  # no body: fine


def test_host_policy_by_bound_address():
    from service.guard import HostPolicy, host_name

    loop = HostPolicy.for_server("127.0.0.1")
    assert all(loop.allows(h) for h in ("localhost", "127.0.0.1:8000", "[::1]:8000", "127.0.0.2", "LOCALHOST."))
    assert not any(loop.allows(h) for h in ("attacker.example", "192.168.1.5", "localhost.attacker.example"))
    assert HostPolicy.for_server("127.0.0.1", ("cam.lan",)).allows("cam.lan:8000")
    assert not HostPolicy.for_server("127.0.0.1", token=True).allows("attacker.example")  # loopback: names only
    wild = HostPolicy.for_server("0.0.0.0")
    assert wild.allows("192.168.1.5:8000") and wild.allows("[fe80::1]") and wild.allows("localhost")
    assert not wild.allows("attacker.example") and not wild.allows("cam.lan")
    assert HostPolicy.for_server("0.0.0.0", ("cam.lan",)).allows("cam.lan")
    assert HostPolicy.for_server("::", token=True).allows("anything.example")
    one = HostPolicy.for_server("192.168.1.5")
    assert one.allows("192.168.1.5:8000") and not one.allows("10.0.0.1") and not one.allows("localhost")
    assert not one.allows("cam.lan") and HostPolicy.for_server("192.168.1.5", token=True).allows("cam.lan")
    assert HostPolicy.for_server("127.0.0.1", ("*",)).allows("anything.example")
    assert host_name("[::1]:80") == "::1" and host_name("::1") == "::1" and host_name("Cam.Lan.:8") == "cam.lan"


def test_origin_and_content_type_rules():
    from service.guard import is_json, origin_allowed

    assert origin_allowed("http://127.0.0.1:8000", "127.0.0.1:8000", ())
    assert not origin_allowed("http://127.0.0.1:8001", "127.0.0.1:8000", ())
    assert not origin_allowed("null", "127.0.0.1:8000", ())
    assert origin_allowed("https://ui.example/", "127.0.0.1:8000", ("https://ui.example",))
    assert origin_allowed("https://any.example", "127.0.0.1:8000", ("*",))
    assert is_json("application/json; charset=utf-8") and is_json("application/merge-patch+json")
    assert not is_json("text/plain") and not is_json("application/x-www-form-urlencoded") and not is_json("")


# ----- HEAD ------------------------------------------------------------------
def test_head_answers_every_get_route_without_a_body(server):
    server.wait_for(lambda s: s["frames"]["reconstructed"] > 0, timeout=60)
    for path, kind in (("/healthz", "application/json"), ("/api/state", "application/json"), ("/", "text/html"),
                       ("/api/settings", "application/json"), ("/snapshot.jpg", "image/jpeg"),
                       ("/snapshot.exr", "image/x-exr"), ("/stream.mjpg", "multipart/x-mixed-replace"),
                       ("/cam/main/api/state", "application/json")):
        t = time.monotonic()
        r = httpx.head(server.url + path, timeout=10)
        assert r.status_code == 200 and r.headers["content-type"].startswith(kind), (path, r.status_code, r.headers)
        assert r.content == b"" and time.monotonic() - t < 5, path
    assert httpx.head(server.url + "/nope", timeout=5).status_code == 404
    # the stream's HEAD left no client behind
    state = server.wait_for(lambda s: s["clients"] == 0 and s["watchers"] == 0)
    assert state["client_list"] == []
    # and a HEAD with a token needs it like a GET does
    with ServerThread(make_camera(fps=5.0, n=2), token="t0ken") as srv:
        assert httpx.head(srv.url + "/api/state", timeout=5).status_code == 401
        assert httpx.head(srv.url + "/healthz", timeout=5).status_code == 200
        assert httpx.head(srv.url + "/api/state", headers={"Authorization": "Bearer t0ken"}, timeout=5).status_code == 200


def test_head_content_length_matches_get(server):
    get = httpx.get(server.url + "/api/settings", timeout=5)
    head = httpx.head(server.url + "/api/settings", timeout=5)
    assert head.headers["content-length"] == get.headers["content-length"] == str(len(get.content))
    assert json.loads(get.content)["jpeg_quality"]
