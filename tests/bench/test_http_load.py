"""The HTTP load client against a stand-in server: one kept-alive connection per stream, failures reported."""

from __future__ import annotations

import json
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
import pytest

from bench.http_load import load_streams

pytestmark = pytest.mark.network


class _FakeDetect(BaseHTTPRequestHandler):
    """POST /detect answering like the service (timing included); stream ids starting 'bench-bad' get 422."""

    protocol_version = "HTTP/1.1"  # keep-alive, as the service's uvicorn
    connections: set[int] = set()

    def do_POST(self) -> None:  # noqa: N802 (http.server's name)
        body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
        _FakeDetect.connections.add(self.client_address[1])
        status = 422 if "bad" in body["stream_id"] else 200
        answer = json.dumps(
            {"stream_id": body["stream_id"], "timestamp": body["timestamp"], "timing": {"model_ms": 1.0}}
            if status == 200
            else {"error": {"code": "x"}}
        ).encode()
        self.send_response(status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(answer)))
        self.end_headers()
        self.wfile.write(answer)

    def log_message(self, *args) -> None:
        pass


def test_http_load_keeps_one_connection_per_stream_and_reports_failures():
    server = ThreadingHTTPServer(("127.0.0.1", 0), _FakeDetect)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    url = f"http://127.0.0.1:{server.server_address[1]}"
    poses = np.zeros((2, 3))
    try:
        result = load_streams(url, ["aaa", "bbb"], poses, streams=3, frames=4, tag="ok")
        assert len(result["latencies"]) == 12 and result["fps"] > 0
        assert {a["stream_id"] for a in result["answers"]} == {f"bench-ok-3-{i}" for i in range(3)}
        assert sorted(a["timestamp"] for a in result["answers"]) == sorted([1000.0 + 0.25 * k for k in range(4)] * 3)
        assert len(_FakeDetect.connections) == 3  # one kept-alive connection per stream, not one per request
        with pytest.raises(RuntimeError, match="2 failed requests"):
            load_streams(url, ["aaa"], poses, streams=1, frames=2, tag="bad")
    finally:
        server.shutdown()
        server.server_close()
