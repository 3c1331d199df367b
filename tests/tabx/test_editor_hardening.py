"""Hostile requests to the editor's HTTP server: bodies are bounded before anything is
read (negative, missing, non-numeric, conflicting or oversized Content-Length), request bodies
go through the strict JSON reader, free-text fields are bounded, a foreign Origin writes
nothing, a request takes exactly one Host and no absolute URI naming another host, connections
beyond the cap get a 503 at once, and the server keeps serving afterwards. Raw sockets to
127.0.0.1 only; every read has a timeout and a byte bound.
"""

from __future__ import annotations

import http.client
import json
import socket
import threading
import time
from pathlib import Path

import pytest

from tabx.editor.server import MAX_BODY, MAX_CONNECTIONS, EditorServer, make_server
from tabx.scenarios.format import MAX_DESCRIPTION

TIMEOUT_S = 5.0  # every socket operation; the server answers these requests in milliseconds
FAST_S = 2.0  # a refusal must come well before the socket timeout: the server did not wait
MAX_RESPONSE = 1 << 20

DUEL = {
    "format": "tabx-scenario/1", "name": "duel", "category": "user",
    "units": [{"unit": "farmer", "team": "ally", "position": [-10.0, 0.0]},
              {"unit": "archer", "team": "enemy", "position": [20.0, 0.0]}],
    "zones": [],
}


@pytest.fixture(scope="module")
def server():
    srv = make_server(0)
    thread = threading.Thread(target=srv.serve_forever, kwargs={"poll_interval": 0.05},
                              daemon=True)
    thread.start()
    yield srv
    srv.shutdown()
    srv.server_close()
    thread.join(TIMEOUT_S)


@pytest.fixture(autouse=True)
def user_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    folder = tmp_path / "user"
    monkeypatch.setenv("TABX_SCENARIO_DIR", str(folder))
    return folder


def connect(server) -> socket.socket:
    host, port = server.server_address[:2]
    assert host == "127.0.0.1"
    return socket.create_connection((host, port), timeout=TIMEOUT_S)


def head(server, method: str, path: str, *headers: str) -> bytes:
    port = server.server_address[1]
    lines = [f"{method} {path} HTTP/1.1", f"Host: 127.0.0.1:{port}", *headers]
    return ("\r\n".join(lines) + "\r\n\r\n").encode()


def read_response(sock: socket.socket) -> tuple[int, dict[str, str], dict | bytes]:
    """One response from `sock` (bounded by the socket timeout and MAX_RESPONSE)."""
    resp = http.client.HTTPResponse(sock)
    resp.begin()
    body = resp.read(MAX_RESPONSE)
    headers = {k.lower(): v for k, v in resp.getheaders()}
    if headers.get("content-type", "").startswith("application/json"):
        return resp.status, headers, json.loads(body)
    return resp.status, headers, body


def exchange(server, data: bytes, shutdown_write: bool = False
             ) -> tuple[int, dict[str, str], dict | bytes, float, bool]:
    """Send `data` (often headers only), read one answer; also whether the server then closed
    the connection (it must, when it left a declared body unread)."""
    with connect(server) as sock:
        t0 = time.monotonic()
        sock.sendall(data)
        if shutdown_write:
            sock.shutdown(socket.SHUT_WR)
        status, headers, body = read_response(sock)
        elapsed = time.monotonic() - t0
        closed = False
        if headers.get("connection", "").lower() == "close":
            sock.settimeout(FAST_S)
            try:
                closed = sock.recv(1) == b""
            except (ConnectionResetError, TimeoutError):
                closed = False
    return status, headers, body, elapsed, closed


def post(server, path: str, body: dict) -> tuple[int, dict]:
    conn = http.client.HTTPConnection("127.0.0.1", server.server_address[1], timeout=TIMEOUT_S)
    try:
        conn.request("POST", path, json.dumps(body).encode(),
                     {"Content-Type": "application/json"})
        resp = conn.getresponse()
        return resp.status, json.loads(resp.read(MAX_RESPONSE))
    finally:
        conn.close()


def get(server, path: str) -> tuple[int, dict]:
    conn = http.client.HTTPConnection("127.0.0.1", server.server_address[1], timeout=TIMEOUT_S)
    try:
        conn.request("GET", path)
        resp = conn.getresponse()
        return resp.status, json.loads(resp.read(MAX_RESPONSE))
    finally:
        conn.close()


def still_serving(server) -> None:
    status, body = get(server, "/api/units")
    assert status == 200 and body["format"] == "tabx-scenario/1"


JSON = "Content-Type: application/json"


@pytest.mark.parametrize("length", ["-200000000", "-1", "-0"])
def test_negative_content_length_is_refused_without_reading(server, length):
    """Only headers are sent: an answer proves the server did not wait for the claimed body."""
    status, headers, body, elapsed, closed = exchange(
        server, head(server, "POST", "/api/validate", JSON, f"Content-Length: {length}"))
    assert status == 400, body
    assert body["ok"] is False and "Content-Length" in body["error"]["message"]
    assert elapsed < FAST_S and closed
    still_serving(server)


@pytest.mark.parametrize("value", ["abc", "12abc", "+5", "1_0", "0x10", "1e3", "5.0", " ",
                                   "99999999999999999999999"])
def test_non_numeric_content_length_is_refused(server, value):
    status, _, body, elapsed, closed = exchange(
        server, head(server, "POST", "/api/validate", JSON, f"Content-Length: {value}"))
    assert status in (400, 411, 413), (value, body)
    assert body["ok"] is False and elapsed < FAST_S and closed
    still_serving(server)


def test_missing_or_chunked_length_is_411(server):
    for extra in ((), ("Transfer-Encoding: chunked",)):
        status, _, body, elapsed, closed = exchange(
            server, head(server, "POST", "/api/save", JSON, *extra))
        assert status == 411, body
        assert "Content-Length" in body["error"]["message"]
        assert elapsed < FAST_S
        if extra:
            assert closed
    still_serving(server)


def test_conflicting_lengths_and_oversized_body(server):
    status, _, body, _, closed = exchange(server, head(
        server, "POST", "/api/validate", JSON, "Content-Length: 5", "Content-Length: 6"))
    assert status == 400 and "conflicting" in body["error"]["message"] and closed
    status, _, body, elapsed, closed = exchange(server, head(
        server, "POST", "/api/validate", JSON, f"Content-Length: {MAX_BODY + 1}"))
    assert status == 413 and elapsed < FAST_S and closed, body
    # Refused for its type before its body: the body is left unread and the connection closed.
    status, _, body, elapsed, closed = exchange(server, head(
        server, "POST", "/api/validate", "Content-Type: text/plain",
        f"Content-Length: {MAX_BODY}"))
    assert status == 415 and elapsed < FAST_S and closed, body
    still_serving(server)


def test_short_body_and_empty_body(server):
    status, _, body, elapsed, _ = exchange(
        server, head(server, "POST", "/api/validate", JSON, "Content-Length: 100") + b'{"a": 1',
        shutdown_write=True)
    assert status == 400 and "ended after 7 of 100 bytes" in body["error"]["message"], body
    assert elapsed < FAST_S
    status, _, body, _, _ = exchange(
        server, head(server, "POST", "/api/validate", JSON, "Content-Length: 0"))
    assert status == 400 and "empty request body" in body["error"]["message"]
    still_serving(server)


def test_get_with_a_body_closes_the_connection(server):
    """A GET that declares a body is answered without waiting for it, and the connection is
    closed: the unread bytes are never parsed as a next request."""
    status, headers, body, elapsed, closed = exchange(
        server, head(server, "GET", "/api/units", "Content-Length: 50000000"))
    assert status == 200 and body["format"] == "tabx-scenario/1"
    assert headers.get("connection", "").lower() == "close" and closed and elapsed < FAST_S
    still_serving(server)


def test_keep_alive_still_works_for_good_requests(server):
    """Two valid POSTs on one connection: the per-request state resets."""
    payload = json.dumps({"scenario": DUEL}).encode()
    one = head(server, "POST", "/api/validate", JSON, f"Content-Length: {len(payload)}") + payload
    with connect(server) as sock:
        for _ in range(2):
            sock.sendall(one)
            status, headers, body = read_response(sock)
            assert status == 200 and body["ok"] is True, body
            assert headers.get("connection", "").lower() != "close"


def test_other_methods_get_a_json_405(server):
    for method in ("PUT", "DELETE", "PATCH"):
        status, headers, body, elapsed, closed = exchange(
            server, head(server, method, "/api/save", JSON, "Content-Length: 1000000"))
        assert status == 405 and body["ok"] is False, (method, body)
        assert headers["allow"] == "GET, HEAD, POST" and closed and elapsed < FAST_S
    still_serving(server)


def test_hostile_json_bodies_are_400_not_500(server):
    cases = {
        b"[" * 200_000 + b"]" * 200_000: "nested deeper than 32",
        b'{"scenario": {}, "scenario": {}}': "appears twice",
        b'{"scenario": {"units": [Infinity]}}': "Infinity is not allowed",
        b"\xff\xfe{}": "not UTF-8",
        b"   ": "empty request body",
    }
    for raw, fragment in cases.items():
        data = head(server, "POST", "/api/validate", JSON, f"Content-Length: {len(raw)}") + raw
        status, _, body, elapsed, _ = exchange(server, data)
        assert status == 400, (raw[:40], body)
        assert fragment in body["error"]["text"], (raw[:40], body)
        assert elapsed < FAST_S
    still_serving(server)


def test_long_free_text_fields_are_bounded(server, user_dir):
    long_description = "x" * (MAX_DESCRIPTION + 1)
    status, body = post(server, "/api/validate",
                        {"scenario": {**DUEL, "description": long_description}})
    assert status == 200 and body["ok"] is False
    assert body["error"]["path"] == "description"
    assert f"at most {MAX_DESCRIPTION} characters" in body["error"]["message"]
    # At the limit it is fine.
    status, body = post(server, "/api/validate",
                        {"scenario": {**DUEL, "description": "x" * MAX_DESCRIPTION}})
    assert status == 200 and body["ok"] is True, body
    # Save refuses it and writes nothing.
    status, body = post(server, "/api/save", {"scenario": {**DUEL, "description": long_description},
                                              "name": "mine", "category": "user"})
    assert status == 400 and body["error"]["path"] == "description"
    assert not user_dir.exists() or not any(user_dir.rglob("*.json"))
    # Long names and controller texts: refused, and the answer does not echo them back.
    huge = "n" * 100_000
    status, body = post(server, "/api/save", {"scenario": DUEL, "name": huge, "category": "user"})
    assert status == 400 and body["error"]["path"] == "name" and len(json.dumps(body)) < 2000
    status, body = post(server, "/api/save", {"scenario": DUEL, "name": "ok", "category": huge})
    assert status == 400 and body["error"]["path"] == "category" and len(json.dumps(body)) < 2000
    status, body = post(server, "/api/preview", {"scenario": DUEL, "steps": 4, "ally": huge,
                                                 "enemy": "random"})
    assert status == 400 and body["error"]["path"] == "ally" and len(json.dumps(body)) < 2000
    status, body = get(server, "/api/scenario?name=" + "a" * 5000)
    assert status == 400 and body["error"]["path"] == "name" and len(json.dumps(body)) < 2000
    still_serving(server)


def test_units_info_serves_the_description_limit(server):
    assert get(server, "/api/units")[1]["max_description"] == MAX_DESCRIPTION


# --- who may ask: Origin, Host, request URI; how many at once ----------------------------------


def save_request(server, *headers: str, path: str = "/api/save", name: str = "mine") -> bytes:
    payload = json.dumps({"scenario": DUEL, "name": name, "category": "user"}).encode()
    return head(server, "POST", path, JSON, f"Content-Length: {len(payload)}",
                *headers) + payload


def test_a_foreign_origin_may_not_write(server, user_dir):
    port = server.server_address[1]
    for origin in ("http://evil.example", "null", f"http://127.0.0.1:{port + 1}",
                   f"https://127.0.0.1:{port}"):
        status, _, body, elapsed, _ = exchange(server, save_request(server, f"Origin: {origin}"))
        assert status == 403 and "another origin" in body["error"]["message"], (origin, body)
        assert elapsed < FAST_S
        assert not user_dir.exists() or not any(user_dir.rglob("*.json"))
    status, _, body, _, _ = exchange(server, head(server, "PUT", "/api/save", JSON,
                                                  "Origin: http://evil.example"))
    assert status == 403, body
    # The page's own origin (either loopback name) saves.
    for i, own in enumerate((f"http://127.0.0.1:{port}", f"http://localhost:{port}")):
        status, _, body, _, _ = exchange(server, save_request(server, f"Origin: {own}",
                                                              name=f"mine{i}"))
        assert status == 200 and body["ok"] is True, body
    still_serving(server)


def test_one_host_and_no_foreign_absolute_uri(server, user_dir):
    port = server.server_address[1]
    status, _, body, _, _ = exchange(server, save_request(server, f"Host: 127.0.0.1:{port}"))
    assert status == 400 and "exactly one Host" in body["error"]["message"], body
    status, _, body, _, _ = exchange(server, save_request(server, "Host: evil.example"))
    assert status == 400, body
    # (`//evil.example/api/save` is a path: http.server folds its leading slashes, a 404.)
    for uri in ("http://evil.example/api/save", f"http://evil.example:{port}/api/save",
                f"ftp://127.0.0.1:{port}/api/save"):
        status, _, body, _, _ = exchange(server, save_request(server, path=uri))
        assert status == 400 and "another host" in body["error"]["message"], (uri, body)
    assert not user_dir.exists() or not any(user_dir.rglob("*.json"))
    status, _, body, _, _ = exchange(server, save_request(
        server, path=f"http://127.0.0.1:{port}/api/save"))
    assert status == 200 and body["ok"] is True, body
    still_serving(server)


def test_connections_beyond_the_cap_get_503_at_once(user_dir):
    srv = EditorServer(0, max_connections=2)
    thread = threading.Thread(target=srv.serve_forever, kwargs={"poll_interval": 0.05},
                              daemon=True)
    thread.start()
    try:
        idle = [connect(srv) for _ in range(2)]  # each holds a thread, sending nothing
        time.sleep(0.2)
        with connect(srv) as extra:
            t0 = time.monotonic()
            status, headers, body = read_response(extra)
            assert status == 503 and body["ok"] is False and time.monotonic() - t0 < FAST_S
            assert headers.get("connection", "").lower() == "close"
        for sock in idle:
            sock.close()
        deadline = time.monotonic() + FAST_S
        while True:  # the idle connections' threads end and free their places
            try:
                still_serving(srv)
                break
            except (AssertionError, http.client.HTTPException, OSError):
                assert time.monotonic() < deadline, "the server stayed full"
                time.sleep(0.05)
        assert MAX_CONNECTIONS >= 8  # a browser's few connections per host fit
    finally:
        srv.shutdown()
        srv.server_close()
        thread.join(TIMEOUT_S)
