"""Issue 39, item 4: every answer that starts before its request's body has arrived says `Connection: close`.

The server closes such a connection after the answer (service/http/head_limits.py: an unread body is not waited for); an
answer that did not say so let a pooled client (nginx's upstream keep-alive, httpx) send its next request on a
connection being closed, and that request failed with "Server disconnected without sending a response". Each early
refusal is provoked here on a real server (the one rafd-serve runs) with a raw socket that sends a head and only part
of its body, and the test reads the answer's header fields and then the end of the connection.
"""

from __future__ import annotations

import contextlib
import json
import socket
import threading
import time
from collections.abc import Iterator

import httpx
import pytest
from starlette.applications import Starlette
from starlette.responses import JSONResponse
from starlette.routing import Route

from service.app import create_app
from service.settings import Settings
from tests.utils.fake_runner import FakeRunner
from tests.utils.service_testing import serve_in_thread, wait_ready

KEY = "early-close-key-0123456789"
PARTIAL_HEAD = "POST {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\nContent-Length: 100000\r\n"


def connect(url: str) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", int(url.rsplit(":", 1)[1])), timeout=10.0)
    return sock


def send_partial(sock: socket.socket, path: str = "/detect", headers: str = "") -> None:
    """A head announcing 100 kB of body, then 1 byte of it: the body is still arriving when the server answers."""
    sock.sendall((PARTIAL_HEAD.format(path=path) + headers + "\r\n").encode() + b"{")


def read_to_eof(sock: socket.socket) -> tuple[int, dict[str, str], dict]:
    """(status, header fields lower-cased, JSON body); returns only once the server closed the connection, so a
    server that kept it open fails the test by the socket's timeout."""
    data = b""
    while chunk := sock.recv(65536):
        data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    fields = {}
    for line in lines[1:]:
        name, _, value = line.partition(":")
        fields[name.strip().lower()] = value.strip()
    return int(lines[0].split(" ")[1]), fields, json.loads(body) if body else {}


@contextlib.contextmanager
def served(runner: FakeRunner | None = None, ready: bool = True, **overrides) -> Iterator[tuple[str, object]]:
    settings = Settings(threads=1, refusal_penalty_s=0.0, **overrides)
    app = create_app(settings, runner=runner or FakeRunner())
    with serve_in_thread(app) as url:
        if ready:
            with httpx.Client(base_url=url, timeout=10.0) as http:
                wait_ready(http)
        yield url, app


def assert_closes(sock: socket.socket, status: int, code: str) -> None:
    got, fields, body = read_to_eof(sock)
    assert got == status, (got, body)
    assert body["error"]["code"] == code
    assert fields.get("connection", "").lower() == "close", fields


@pytest.mark.network
def test_401_before_the_body_says_connection_close():
    with served(api_keys=[KEY]) as (url, app), connect(url) as sock:
        send_partial(sock)
        assert_closes(sock, 401, "missing_api_key")


@pytest.mark.network
def test_408_body_timeout_says_connection_close():
    with served(body_timeout_s=0.3, min_body_bytes_per_s=0) as (url, app), connect(url) as sock:
        send_partial(sock, headers="X-Stream-Id: s\r\n")
        assert_closes(sock, 408, "body_timeout")


@pytest.mark.network
def test_408_body_too_slow_says_connection_close():
    with served(body_rate_grace_s=0.2) as (url, app), connect(url) as sock:
        send_partial(sock)
        assert_closes(sock, 408, "body_too_slow")


@pytest.mark.network
def test_413_from_content_length_says_connection_close():
    with served(max_request_bytes=50_000) as (url, app), connect(url) as sock:
        send_partial(sock)
        assert_closes(sock, 413, "request_too_large")


@pytest.mark.network
@pytest.mark.parametrize(
    ("limit", "first_headers", "second_headers", "status", "code"),
    [
        # the first request, unfinished, holds the one place the limit allows; the second is refused early
        ({"stream_queue_limit": 1}, "X-Stream-Id: s\r\n", "X-Stream-Id: s\r\n", 429, "stream_queue_full"),
        ({"max_requests_per_client": 1}, "", "", 429, "too_many_client_requests"),
        ({"max_receiving_requests": 1}, "X-Stream-Id: a\r\n", "X-Stream-Id: b\r\n", 503, "overloaded"),
    ],
)
def test_a_refusal_while_another_request_holds_the_place_says_connection_close(
    limit: dict[str, int], first_headers: str, second_headers: str, status: int, code: str
):
    with served(**limit, body_timeout_s=5.0, min_body_bytes_per_s=0) as (url, app):
        with connect(url) as first, connect(url) as second:
            send_partial(first, headers=first_headers)
            wait_receiving(app)
            send_partial(second, headers=second_headers)
            assert_closes(second, status, code)


@pytest.mark.network
def test_503_not_ready_says_connection_close():
    gate = threading.Event()  # the warm-up step waits at the gate: the model is not ready meanwhile
    try:
        with served(runner=FakeRunner(gate=gate), ready=False) as (url, app), connect(url) as sock:
            send_partial(sock, headers="X-Stream-Id: s\r\n")
            assert_closes(sock, 503, "not_ready")
    finally:
        gate.set()


@pytest.mark.network
@pytest.mark.parametrize("status", [200, 403, 409, 503])
def test_any_answer_before_its_body_says_connection_close_and_a_full_body_keeps_the_connection(status):
    """The rule is the server's, not each refusal's: any answer (403 here: the service has no 403 of its own yet)
    that starts before its request's body arrived says `Connection: close`; one whose body had arrived keeps the
    connection for the next request."""

    async def early(request):
        return JSONResponse({"error": {"code": "x", "message": "refused unread"}}, status_code=status)

    app = Starlette(routes=[Route("/early", early, methods=["POST"])])
    with serve_in_thread(app, Settings(threads=1)) as url:
        with connect(url) as sock:
            send_partial(sock, path="/early")
            got, fields, _ = read_to_eof(sock)
            assert got == status and fields.get("connection") == "close"
        with connect(url) as sock:  # the whole body sent: answered and kept alive, a second request is answered
            request = b"POST /early HTTP/1.1\r\nHost: x\r\nContent-Length: 2\r\n\r\n{}"
            sock.sendall(request + request)
            data = b""
            while data.count(b"HTTP/1.1 ") < 2:
                chunk = sock.recv(65536)
                assert chunk, f"closed after {data!r}"
                data += chunk
            assert b"connection: close" not in data.lower()


@pytest.mark.network
def test_a_pooled_client_gets_every_answer_after_an_early_401():
    """The issue's failure: a pooled httpx client's next request after a 401 on an unread body."""
    with served(api_keys=[KEY]) as (url, _), httpx.Client(base_url=url, timeout=10.0) as http:
        big = b'{"stream_id": "s", "timestamp": 1, "image": "' + b"A" * 1_000_000 + b'"}'
        refused = http.post("/detect", content=big, headers={"content-type": "application/json"})
        assert refused.status_code == 401 and refused.headers["connection"] == "close"
        for _ in range(3):  # each on a connection the server keeps (or a new one): never a disconnect
            assert http.get("/health/live").status_code == 200


def wait_receiving(app, count: int = 1) -> None:
    """Until `count` /detect requests are receiving their body (the server runs in this process), bounded."""
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline:
        service = app.state.service
        if service is not None and service.receiving.in_flight >= count:
            return
        time.sleep(0.01)
    raise AssertionError(f"not {count} requests receiving their body within 10 s")
