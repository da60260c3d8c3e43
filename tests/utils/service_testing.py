"""Helpers shared by the service tests: PNG frames, posting, waiting for readiness."""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator
from typing import Any

import numpy as np
import uvicorn
from fastapi.testclient import TestClient

from rafd.detect_client import FrameFields, base64_png, json_body
from rafd.detect_client import png_bytes as png


def b64png(image: np.ndarray) -> str:
    return base64_png(png(image))


def blob_frame(size: int, spots: list[tuple[int, int, int]], background: int = 0) -> np.ndarray:
    """[size, size] uint8 with 4x4 bright squares at (row, col) pixel corners with the given value."""
    image = np.full((size, size), background, np.uint8)
    for row, col, value in spots:
        image[row : row + 4, col : col + 4] = value
    return image


def detect_json(
    stream_id: str, timestamp: float, image: np.ndarray, pose: tuple[float, float, float] | None = None
) -> dict[str, Any]:
    """A /detect JSON body as a dict (to post with a test client's json=, or to change first)."""
    return FrameFields(timestamp, stream_id, pose).json_fields(b64png(image))


def wait_ready(client: Any, timeout: float = 10.0) -> None:
    """The model loads in a background task of the lifespan: poll readiness."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if client.get("/health/ready").status_code == 200:
            return
        time.sleep(0.01)
    raise AssertionError(f"service not ready after {timeout} s: {client.get('/health/ready').json()}")


def stream_state(client: TestClient, stream_id: str) -> dict[str, Any] | None:
    """The stream's row of GET /streams (None when unknown), minus the idle time."""
    for row in client.get("/streams").json()["streams"]:
        if row["stream_id"] == stream_id:
            return {k: v for k, v in row.items() if k != "idle_s"}
    return None


class FakeOdometry:
    """Constant ego motion per frame; records the frames it was given."""

    def __init__(self, motion: tuple[float, float, float] = (0.5, 2.0, 0.1)) -> None:
        self.motion = np.array(motion)
        self.calls: list[tuple[np.ndarray, np.ndarray, float]] = []

    def __call__(self, previous: np.ndarray, current: np.ndarray, resolution: float) -> np.ndarray:
        self.calls.append((previous.copy(), current.copy(), resolution))
        return self.motion.copy()


@contextlib.contextmanager
def serve_in_thread(app: Any, settings: Any = None) -> Iterator[str]:
    """Run `app` on a free loopback port under the server `rafd-serve` runs (service/http/server.py: uvicorn with the
    service's HTTP protocol and limits; `settings`: the app's own by default); yields its base URL."""
    from service.http.server import server_config

    config = server_config(app, settings or app.state.settings, host="127.0.0.1", port=0, log_level="warning")
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 10.0
    while not server.started:
        if time.monotonic() > deadline or not thread.is_alive():
            raise AssertionError("uvicorn did not start")
        time.sleep(0.01)
    port = server.servers[0].sockets[0].getsockname()[1]
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(timeout=10.0)


def wait_until(predicate: Any, timeout: float = 10.0, message: str = "condition") -> None:
    """Poll `predicate()` until it is true (state reached by other threads), else fail naming `message`."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {message}")
        time.sleep(0.005)


def http_request(
    method: str, path: str, body: bytes = b"", headers: dict[str, str] | None = None
) -> tuple[bytes, bytes]:
    """(head, body) of a raw HTTP/1.1 request that closes its connection, to send in pieces over a socket."""
    lines = [
        f"{method} {path} HTTP/1.1",
        "Host: 127.0.0.1",
        "Connection: close",
        f"Content-Length: {len(body)}",
        *(f"{k}: {v}" for k, v in (headers or {}).items()),
    ]
    return ("\r\n".join(lines) + "\r\n\r\n").encode("latin-1"), body


def read_http_response(sock: Any, timeout: float = 10.0) -> tuple[int, bytes]:
    """Read a whole `Connection: close` response: (status, body)."""
    sock.settimeout(timeout)
    data = b""
    while chunk := sock.recv(65536):
        data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    return int(head.split(b" ", 2)[1]), body


def json_part(
    stream_id: str, timestamp: float, image: np.ndarray, pose: tuple[float, float, float] | None = None
) -> bytes:
    """A /detect JSON body as bytes."""
    return json_body(FrameFields(timestamp, stream_id, pose), b64png(image)).content
