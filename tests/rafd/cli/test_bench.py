"""rafd-bench on the shipped model, model paths only (the service itself is exercised by the service tests): every
runtime and precision side by side, the matmul peaks, the concurrency comparison and the accuracy gate; and its
HTTP load client against a stand-in server."""
from __future__ import annotations

import json
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pytest

from rafd.cli.bench import load_streams, main, time_interleaved
from rafd.runtime import supported_choices


def test_bench_reports_every_runtime_side_by_side_and_writes_json(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                                  monkeypatch: pytest.MonkeyPatch):
    monkeypatch.delenv("RAFD_RADIATE_SAMPLE", raising=False)  # simulated gate frames only: keeps the test short
    out = tmp_path / "bench.json"
    assert main(["--configs", "default", "--no-http", "--repeats", "2", "--threads", "1", "--concurrency-frames", "2",
                 "--gate-sequences", "1", "--gate-frames", "6", "--json", str(out)]) == 0
    table = capsys.readouterr().out
    choices = [f"{r}/{p}" for r, p in supported_choices()]
    for path in ["pytorch eager, full window", "onnxruntime fp32, full window"] + [f"streaming step, {c}" for c in choices]:
        assert f"| default | {path} |" in table
    figures = json.loads(out.read_text())
    facts, machine = figures["facts"]["default"], figures["facts"]["machine"]
    assert facts["num_frames"] == 4 and facts["gflop_per_window"] > facts["gflop_per_step"] > 0
    assert facts["stream_state_bytes"] > 0 and set(facts["achieved_tflops_streaming"]) == set(choices)
    assert machine["matmul_peak_gflops"]["fp32"] > 0 and machine["matmul_peak_gflops"]["bf16"] > 0
    assert set(facts["concurrency"]) == {f"{c}, 1 concurrent run(s)" for c in choices}  # 1 thread: one mode
    reduced = [c for c in choices if not c.endswith("fp32")]
    assert set(facts["gate"]) == set(reduced)
    for gate in facts["gate"].values():
        assert gate["verdict"] in ("PASS", "FAIL") and gate["figures"]["simulated"]["frames"] == 6 - 3
    assert all(row["p50_ms"] > 0 for row in figures["rows"])


@pytest.mark.parametrize("argv,message", [(["--configs", "huge"], "huge"),
                                          (["--http-runtimes", "openvino"], "runtime/precision")])
def test_bench_refuses_bad_arguments(capsys: pytest.CaptureFixture[str], argv, message):
    assert main(argv) == 2
    assert message in capsys.readouterr().err


def test_interleaved_timing_is_not_charged_for_the_path_before():
    """A run can leave work behind it (onnxruntime's pool threads spin on the cores after a run returns): the path
    timed next must not pay for it. Here every call pays 20 ms when another path ran just before it, 0 otherwise."""
    last = {"name": None}

    def path(name: str):
        def call(_: int) -> None:
            if last["name"] not in (None, name):
                time.sleep(0.02)  # the previous path's leftover work
            last["name"] = name
        return call

    samples = time_interleaved({"a": path("a"), "b": path("b")}, repeats=3)
    assert set(samples) == {"a", "b"} and all(len(s) == 3 for s in samples.values())
    assert max(max(s) for s in samples.values()) < 0.01


class _FakeDetect(BaseHTTPRequestHandler):
    """POST /detect answering like the service (timing included); stream ids starting 'bench-bad' get 422."""

    protocol_version = "HTTP/1.1"  # keep-alive, as the service's uvicorn
    connections: set[int] = set()

    def do_POST(self) -> None:  # noqa: N802 (http.server's name)
        body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
        _FakeDetect.connections.add(self.client_address[1])
        status = 422 if "bad" in body["stream_id"] else 200
        answer = json.dumps({"stream_id": body["stream_id"], "timestamp": body["timestamp"],
                             "timing": {"model_ms": 1.0}} if status == 200 else {"error": {"code": "x"}}).encode()
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
