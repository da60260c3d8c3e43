"""Hardening of the service against clients, each attack reproduced as it was first probed, now refused or handled:

- one client cannot stall everyone (padded PNGs refused from their chunk headers; one bounded executor per stage);
- made-up HTTP methods add no metric series;
- a stream's frames are served in arrival order (no spurious 409s);
- DELETE during in-flight requests ends the chain cleanly;
- refused requests do not touch the stream (LRU position, idle time);
- client disconnects are 499, never 500;
- error bodies do not grow with the input;
- every error code is documented (docs/api.md) and in the OpenAPI responses (the case table is body/test_bad_input.py).
"""

from __future__ import annotations

import contextlib
import json
import logging
import re
import select
import socket
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

import service.body.images
import service.pipeline.detector
from service.app import create_app
from service.http.errors import ERRORS
from service.settings import Settings
from tests.utils.answers_testing import chain_free
from tests.utils.fake_runner import WARM_UP_RUNS, FakeRunner
from tests.utils.png_testing import grey_png, padded_scan
from tests.utils.service_testing import (
    blob_frame,
    detect_json,
    http_request,
    json_part,
    png,
    read_http_response,
    serve_in_thread,
    stream_state,
    wait_ready,
    wait_until,
)

REPO = Path(__file__).resolve().parents[2]
FRAME = blob_frame(128, [(8, 8, 255)])


def uniform(i: int) -> np.ndarray:
    """Frame i is uniform 8 * i: the fake runner's flow x reveals which frame preceded it."""
    return np.full((128, 128), 8 * i, np.uint8)


def predecessor(answer: dict, i: int) -> int:
    return round(i - answer["flow"]["values"][0][0][0] / 8.0)


@contextlib.contextmanager
def gated_app(**overrides):
    """An app whose model step blocks until `gate.set()` (warm-up already done): frames pile up in flight."""
    gate = threading.Event()
    gate.set()
    runner = FakeRunner(gate=gate)
    # one model step at a time; one test client posts every frame: neither its request limit nor the parse queue
    # is what these tests are about
    limits = {"max_requests_per_client": 256, "parse_queue_limit": 256} | overrides
    settings = Settings(threads=1, concurrent_runs=1, **limits)
    with TestClient(create_app(settings, runner=runner)) as client:
        wait_ready(client)
        gate.clear()
        try:
            yield client, gate, runner
        finally:
            gate.set()


def queued(client: TestClient, executor: str) -> float:
    match = re.search(rf'rafd_executor_queued{{executor="{executor}"}} ([0-9.]+)', client.get("/metrics").text)
    return float(match.group(1)) if match else -1.0


# ------------------------------------------------------------------------------------- one client cannot stall everyone
@pytest.fixture(scope="module")
def scan_png(tmp_path_factory) -> bytes:
    """A valid 1152 px greyscale scan like RADIATE's (speckle, so it compresses like a real one)."""
    rng = np.random.default_rng(0)
    return png(rng.integers(0, 40, (1152, 1152), dtype=np.uint8))


def test_padded_png_is_refused_from_its_chunk_headers_without_decoding(monkeypatch, scan_png):
    padded = padded_scan(scan_png)  # ~900 zTXt chunks, 7.7 MB: ~27 s of libpng time here before the fix
    assert 7_000_000 < len(padded) < 8 * 1024 * 1024
    decoded = []
    monkeypatch.setattr(service.body.images.cv2, "imdecode", lambda *a: decoded.append(1))
    with TestClient(create_app(Settings(threads=1, max_request_bytes=8 * 1024 * 1024), runner=FakeRunner())) as client:
        wait_ready(client)
        response = client.post(
            "/detect", data={"stream_id": "flood", "timestamp": "1"}, files={"image": ("x.png", padded, "image/png")}
        )
    assert response.status_code == 422 and response.json()["error"]["code"] == "invalid_image"
    assert "ancillary chunks" in response.json()["error"]["message"]
    assert decoded == []  # refused before any decode


def test_image_data_past_its_header_is_refused_before_decoding(monkeypatch):
    bomb = grey_png(FRAME, extra_compressed=50_000_000)  # 50 MB of zeros after the last row: libpng inflates all
    decoded = []
    monkeypatch.setattr(service.body.images.cv2, "imdecode", lambda *a: decoded.append(1))
    with TestClient(create_app(Settings(threads=1), runner=FakeRunner())) as client:
        wait_ready(client)
        response = client.post("/detect", json=detect_json("bomb", 1.0, FRAME) | {"image": _b64(bomb)})
    assert response.status_code == 422 and "inflates to more than" in response.json()["error"]["message"]
    assert decoded == []


def test_a_few_ancillary_chunks_are_dropped_and_the_frame_served(monkeypatch):
    """RADIATE's own scans carry a tIME chunk: allowed, and stripped before the decoder sees the file."""
    from tests.utils.png_testing import chunk, text_chunks

    seen = []
    real = cv2.imdecode
    monkeypatch.setattr(
        service.body.images.cv2, "imdecode", lambda buf, flags: seen.append(bytes(buf)) or real(buf, flags)
    )
    image = grey_png(FRAME, before_idat=chunk(b"tIME", bytes(7)) + text_chunks(3, 1000), interlaced=True)
    with TestClient(create_app(Settings(threads=1), runner=FakeRunner())) as client:
        wait_ready(client)
        plain = client.post("/detect", json=detect_json("plain", 1.0, FRAME, (0, 0, 0))).json()
        response = client.post("/detect", json=detect_json("padded", 1.0, FRAME, (0, 0, 0)) | {"image": _b64(image)})
    assert response.status_code == 200, response.text
    assert chain_free(response.json()["boxes"]) == chain_free(plain["boxes"])  # the interlaced file: the same pixels
    assert b"tIME" not in seen[-1] and b"zTXt" not in seen[-1]


def test_health_and_metrics_answer_while_the_model_queue_is_full_and_excess_work_gets_503():
    """45 frames in flight behind a blocked model (the issue's load): readiness and metrics still answer at once,
    the model queue holds its limit, and the rest are refused at once with 503 + Retry-After."""
    with gated_app(model_queue_limit=4, retry_after_s=2) as (client, gate, runner):
        with ThreadPoolExecutor(max_workers=45) as pool:
            futures = [
                pool.submit(client.post, "/detect", json=detect_json(f"s{k}", 1.0, FRAME, (0, 0, 0))) for k in range(45)
            ]
            wait_until(lambda: queued(client, "model") == 4, message="the model queue to fill")
            wait_until(lambda: sum(f.done() for f in futures) == 40, message="the excess to be refused")
            # the model is still blocked: these must not wait behind it
            assert client.get("/health/ready").status_code == 200
            assert client.get("/health/live").status_code == 200
            assert "rafd_executor_refused_total" in client.get("/metrics").text
            refused = [f.result() for f in futures if f.done()]
            gate.set()
            answers = [f.result() for f in futures]
    assert all(r.status_code == 503 and r.json()["error"]["code"] == "overloaded" for r in refused)
    assert all(r.headers["retry-after"] == "2" for r in refused)
    assert sum(r.status_code == 200 for r in answers) == 5  # 1 running + 4 queued
    assert runner.calls == WARM_UP_RUNS + 5  # the admitted frames: refused work was never spent


def test_in_flight_limit_refuses_once_the_body_has_arrived():
    with gated_app(max_inflight_requests=2) as (client, gate, runner):
        with ThreadPoolExecutor(max_workers=2) as pool:
            futures = [
                pool.submit(client.post, "/detect", json=detect_json(f"s{k}", 1.0, FRAME, (0, 0, 0))) for k in range(2)
            ]
            wait_until(lambda: runner.at_gate + queued(client, "model") == 2, message="two frames in flight")
            third = client.post("/detect", json=detect_json("s3", 1.0, FRAME, (0, 0, 0)))
            gate.set()
            assert all(f.result().status_code == 200 for f in futures)
    assert third.status_code == 503 and "RAFD_MAX_INFLIGHT_REQUESTS" in third.json()["error"]["message"]
    assert third.headers["retry-after"] == "1"


# ------------------------------------------------------------------------------------------------- closed metric labels
def test_made_up_http_methods_add_no_metric_series(client):
    before = client.get("/metrics").text.count("rafd_requests_total{")
    for k in range(200):
        client.request(f"PROBE{k}", "/detect")
        client.request(f"X{k}", f"/made/up/{k}")
    text = client.get("/metrics").text
    assert "PROBE" not in text and "/made/up" not in text
    assert 'rafd_requests_total{code="405",method="other",route="/detect"} 200.0' in text
    assert 'rafd_requests_total{code="404",method="other",route="unmatched"} 200.0' in text
    assert text.count("rafd_requests_total{") <= before + 3  # the two series above and the /metrics GET


# -------------------------------------------------------------------------------------------------------- arrival order
def test_frames_sent_in_order_on_separate_connections_are_all_served_in_that_order(monkeypatch):
    """Later frames decode faster (as a small crop after a full scan would); before the fix they overtook the
    earlier ones and got spurious 409s. Now each takes its place on arrival, before decoding."""
    count = 6
    real = service.pipeline.detector.decode_frame

    def slow_early_frames(image, size, resolution, *native):
        decoded = real(image, size, resolution, *native)
        time.sleep(0.02 * (count + 1 - decoded.covered[0, 0] // 8))  # frame i: (count + 1 - i) * 20 ms
        return decoded

    monkeypatch.setattr(service.pipeline.detector, "decode_frame", slow_early_frames)
    settings = Settings(threads=1, decode_workers=count)  # decodes run in parallel, so they could overtake
    with TestClient(create_app(settings, runner=FakeRunner())) as client:
        wait_ready(client)
        with ThreadPoolExecutor(max_workers=count) as pool:
            futures = []
            for i in range(1, count + 1):
                futures.append(
                    pool.submit(
                        client.post, "/detect", json=detect_json("ordered", float(i), uniform(i), (float(i), 0, 0))
                    )
                )
                time.sleep(0.01)  # sent 10 ms apart, in timestamp order
            answers = [f.result() for f in futures]
    assert [a.status_code for a in answers] == [200] * count, [a.text for a in answers]
    for i, answer in enumerate(answers[1:], start=2):
        assert predecessor(answer.json(), i) == i - 1


def test_with_the_stream_named_in_a_header_a_frame_is_placed_before_its_body_arrives():
    """Frame A's headers arrive, its body later; frame B arrives whole in between. B waits for A."""
    app = create_app(Settings(threads=1), runner=FakeRunner())
    with serve_in_thread(app) as url, httpx.Client(base_url=url, timeout=10.0) as http:
        wait_ready(http)
        assert http.post("/detect", json=detect_json("hdr", 1.0, uniform(1), (1.0, 0, 0))).status_code == 200
        port = int(url.rsplit(":", 1)[1])
        head_a, body_a = http_request(
            "POST",
            "/detect",
            json_part("hdr", 2.0, uniform(2), (2.0, 0, 0)),
            {"Content-Type": "application/json", "X-Stream-Id": "hdr"},
        )
        head_b, body_b = http_request(
            "POST",
            "/streams/hdr/detect",
            json_part("hdr", 3.0, uniform(3), (3.0, 0, 0)),
            {"Content-Type": "application/json"},
        )
        with socket.create_connection(("127.0.0.1", port)) as a, socket.create_connection(("127.0.0.1", port)) as b:
            a.sendall(head_a)
            wait_until(lambda: stream_state(http, "hdr")["frames_queued"] == 1, message="A to take its place")
            b.sendall(head_b + body_b)
            wait_until(lambda: stream_state(http, "hdr")["frames_queued"] == 2, message="B to queue behind A")
            assert select.select([b], [], [], 0.3)[0] == []  # B is not answered while A's body is missing
            a.sendall(body_a)
            status_a, answer_a = read_http_response(a)
            status_b, answer_b = read_http_response(b)
    assert (status_a, status_b) == (200, 200), (answer_a, answer_b)
    assert predecessor(json.loads(answer_a), 2) == 1
    assert predecessor(json.loads(answer_b), 3) == 2 and json.loads(answer_b)["flow"]["pair"] == [2.0, 3.0]


def test_a_slow_body_holds_its_streams_place_only_until_the_body_timeout():
    # frame 2 is lost to the timeout: the gap rule must not restart the chain over the 2 s from frame 1 to 3
    app = create_app(Settings(threads=1, body_timeout_s=0.5, stream_gap_restart_s=10.0), runner=FakeRunner())
    with serve_in_thread(app) as url, httpx.Client(base_url=url, timeout=10.0) as http:
        wait_ready(http)
        assert http.post("/detect", json=detect_json("slow", 1.0, uniform(1), (1.0, 0, 0))).status_code == 200
        port = int(url.rsplit(":", 1)[1])
        head, _ = http_request(
            "POST",
            "/streams/slow/detect",
            json_part("slow", 2.0, uniform(2), (2.0, 0, 0)),
            {"Content-Type": "application/json"},
        )
        with socket.create_connection(("127.0.0.1", port)) as stalled:
            stalled.sendall(head)  # ... and never the body
            wait_until(lambda: stream_state(http, "slow")["frames_queued"] == 1, message="the stalled frame queued")
            behind = http.post("/detect", json=detect_json("slow", 3.0, uniform(3), (3.0, 0, 0)))
            status, answer = read_http_response(stalled)
    assert status == 408 and json.loads(answer)["error"]["code"] == "body_timeout"
    assert behind.status_code == 200 and predecessor(behind.json(), 3) == 1


def test_a_frame_that_can_no_longer_be_in_order_is_refused_without_waiting():
    with gated_app() as (client, gate, runner):
        with ThreadPoolExecutor(max_workers=1) as pool:
            running = pool.submit(client.post, "/detect", json=detect_json("late", 5.0, FRAME, (0, 0, 0)))
            wait_until(lambda: runner.at_gate == 1, message="frame 5 in the model")
            stale = client.post("/detect", json=detect_json("late", 3.0, FRAME, (0, 0, 0)))  # answered while blocked
            gate.set()
            assert running.result().status_code == 200
    assert stale.status_code == 409 and "arrived earlier and is still queued" in stale.json()["error"]["message"]


# --------------------------------------------------------------------------------------- DELETE during in-flight frames
def test_delete_ends_the_chain_and_its_queued_frames_are_refused():
    with gated_app() as (client, gate, runner):
        gate.set()
        for t in (1.0, 2.0):
            assert client.post("/detect", json=detect_json("d", t, FRAME, (t, 0, 0))).status_code == 200
        gate.clear()
        with ThreadPoolExecutor(max_workers=3) as pool:
            running = pool.submit(client.post, "/detect", json=detect_json("d", 3.0, FRAME, (3.0, 0, 0)))
            wait_until(lambda: runner.at_gate == 1, message="frame 3 in the model")
            waiting = pool.submit(client.post, "/detect", json=detect_json("d", 4.0, FRAME, (4.0, 0, 0)))
            wait_until(lambda: stream_state(client, "d")["frames_queued"] == 2, message="frame 4 queued")
            assert client.delete("/streams/d").status_code == 204
            assert waiting.result().status_code == 409  # refused at once, the model still blocked
            fresh = pool.submit(client.post, "/detect", json=detect_json("d", 10.0, FRAME, (10.0, 0, 0)))
            gate.set()
            answers = {"running": running.result(), "waiting": waiting.result(), "fresh": fresh.result()}
        final = stream_state(client, "d")
    assert answers["running"].status_code == 409 and answers["running"].json()["error"]["code"] == "stream_reset"
    assert answers["waiting"].json()["error"]["code"] == "stream_reset"
    assert answers["fresh"].status_code == 200 and answers["fresh"].json()["frames_used"] == 1
    assert final["generation"] == 2 and final["frames_seen"] == 1 and final["last_timestamp"] == 10.0


# -------------------------------------------------------------------------------- refused frames leave the stream alone
class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def test_refused_frames_do_not_move_a_stream_in_the_lru_order():
    clock = Clock()
    with TestClient(create_app(Settings(threads=1, max_streams=2), runner=FakeRunner(), clock=clock)) as client:
        wait_ready(client)
        client.post("/detect", json=detect_json("a", 1.0, FRAME, (0, 0, 0)))
        clock.now += 10
        client.post("/detect", json=detect_json("b", 1.0, FRAME, (0, 0, 0)))
        clock.now += 10
        for refused in (detect_json("a", 0.5, FRAME), detect_json("a", 2.0, FRAME) | {"image": "AAAA"}):
            assert client.post("/detect", json=refused).status_code in (409, 422)
        clock.now += 10
        client.post("/detect", json=detect_json("c", 1.0, FRAME, (0, 0, 0)))  # at the cap: evicts the LRU
        names = [s["stream_id"] for s in client.get("/streams").json()["streams"]]
    assert names == ["b", "c"]  # "a" was least recently ACCEPTED; before the fix "b" was evicted


def test_a_stream_fed_only_refused_frames_expires_at_its_ttl():
    clock = Clock()
    with TestClient(create_app(Settings(threads=1, stream_ttl_s=60), runner=FakeRunner(), clock=clock)) as client:
        wait_ready(client)
        client.post("/detect", json=detect_json("a", 1.0, FRAME, (0, 0, 0)))
        for _ in range(5):
            clock.now += 11
            assert client.post("/detect", json=detect_json("a", 0.5, FRAME)).status_code == 409
        assert stream_state(client, "a") is not None  # 55 s idle
        clock.now += 6
        assert stream_state(client, "a") is None  # 61 s after its last accepted frame
        assert 'rafd_stream_evictions_total{reason="ttl"} 1.0' in client.get("/metrics").text


# --------------------------------------------------------------------------------------------------- client disconnects
class Records(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


@contextlib.contextmanager
def captured_logs():
    """Every record of the service and of uvicorn (whose loggers do not propagate to the root)."""
    handler = Records()
    loggers = [logging.getLogger(), logging.getLogger("uvicorn"), logging.getLogger("uvicorn.error")]
    service_logger = logging.getLogger("service")
    level = service_logger.level
    service_logger.setLevel(logging.INFO)
    for logger in loggers:
        logger.addHandler(handler)
    try:
        yield handler.records
    finally:
        for logger in loggers:
            logger.removeHandler(handler)
        service_logger.setLevel(level)


def test_client_disconnects_are_499_with_one_info_line_never_500():
    gate = threading.Event()
    gate.set()
    runner = FakeRunner(gate=gate)
    app = create_app(Settings(threads=1), runner=runner)
    with captured_logs() as records, serve_in_thread(app) as url, httpx.Client(base_url=url, timeout=10.0) as http:
        wait_ready(http)
        port = int(url.rsplit(":", 1)[1])
        # 1. leaves half-way through its body
        head, body = http_request(
            "POST", "/detect", json_part("cut", 1.0, FRAME, (0, 0, 0)), {"Content-Type": "application/json"}
        )
        with socket.create_connection(("127.0.0.1", port)) as sock:
            sock.sendall(head + body[: len(body) // 2])
        wait_until(lambda: 'code="499"' in http.get("/metrics").text, message="the first 499")
        # 2. leaves while its frame waits behind another frame of its stream: dropped, the stream unchanged
        assert http.post("/detect", json=detect_json("wait", 1.0, FRAME, (0, 0, 0))).status_code == 200
        gate.clear()
        with ThreadPoolExecutor(max_workers=1) as pool:
            running = pool.submit(http.post, "/detect", json=detect_json("wait", 2.0, FRAME, (1.0, 0, 0)))
            wait_until(lambda: runner.at_gate == 1, message="frame 2 in the model")
            head, body = http_request(
                "POST", "/detect", json_part("wait", 3.0, FRAME, (2.0, 0, 0)), {"Content-Type": "application/json"}
            )
            with socket.create_connection(("127.0.0.1", port)) as sock:
                sock.sendall(head + body)
                wait_until(lambda: stream_state(http, "wait")["frames_queued"] == 2, message="frame 3 queued")
            time.sleep(0.1)  # the server sees the connection close while frame 3 waits
            gate.set()
            assert running.result().status_code == 200
        wait_until(
            lambda: 'rafd_requests_total{code="499",method="POST",route="/detect"} 2.0' in http.get("/metrics").text,
            message="the second 499",
        )
        metrics = http.get("/metrics").text
        state = stream_state(http, "wait")
    assert 'code="500"' not in metrics
    assert state["frames_seen"] == 2 and state["last_timestamp"] == 2.0  # the abandoned frame 3 was dropped
    lines = [r for r in records if "disconnected" in r.getMessage()]
    assert len(lines) == 2 and all(r.levelno == logging.INFO for r in lines)
    assert not [r for r in records if r.levelno >= logging.ERROR], [r.getMessage() for r in records]


# ------------------------------------------------------------------------------------------------- bounded error bodies
def test_error_bodies_do_not_grow_with_the_input(client):
    body = detect_json("s", 1.0, FRAME) | {f"extra_key_{k}": k for k in range(100_000)}  # ~1.8 MB
    response = client.post("/detect", json=body)
    assert response.status_code == 422 and len(response.content) < 1024
    assert "more than a detect request can have" in response.json()["error"]["message"]  # refused unparsed
    body = detect_json("s", 1.0, FRAME) | {f"extra_key_{k}": k for k in range(20)}  # parsed: the keys are listed
    response = client.post("/detect", json=body)
    assert response.status_code == 422 and "and 15 more" in response.json()["error"]["message"]
    nested = detect_json("s", 1.0, FRAME) | {"pose": {f"k{k}": 0 for k in range(100_000)}}
    response = client.post("/detect", json=nested)
    assert response.status_code == 422 and len(response.content) < 1024
    wrong = client.post("/detect", json=detect_json("s", 1.0, FRAME) | {"x" * 500_000: 1})
    assert wrong.status_code == 422 and len(wrong.content) < 1024


# ------------------------------------------------------------------------------------------------ every code documented
def test_every_error_code_is_documented_in_the_docs_and_the_openapi_responses(client):
    from tools.api_tables import API_DOC, with_table

    page = API_DOC.read_text()
    assert with_table(page) == page, "docs/api.md's error table is not ERRORS': python -m tools.api_tables --write"
    spec = client.get("/openapi.json").json()
    described = json.dumps(spec["paths"]) + spec["info"]["description"]  # per route + any route's
    for code, error in ERRORS.items():
        assert f"| {error.status} | `{code}` |" in page, f"{code} is not in docs/api.md's table"
        assert f"`{code}`" in described, f"{code} is not in the OpenAPI spec"
    # and the source raises only registered codes (ApiError would fail at run time; this catches dead paths too)
    raised = set()
    for path in (REPO / "service").rglob("*.py"):
        raised |= set(re.findall(r'ApiError\(\s*"([a-z_]+)"', path.read_text()))
    assert raised and raised <= set(ERRORS)


def test_openapi_says_metrics_is_text_and_detect_lists_its_errors(client):
    spec = client.get("/openapi.json").json()
    assert set(spec["paths"]["/metrics"]["get"]["responses"]["200"]["content"]) == {"text/plain"}
    responses = spec["paths"]["/detect"]["post"]["responses"]
    assert {"400", "401", "408", "409", "413", "415", "422", "429", "500", "503"} <= set(responses)
    assert "403" not in responses  # a stream id lives in its key's namespace: no other key's stream to refuse
    assert "bad_request" not in json.dumps(spec)
    assert spec["paths"]["/streams/{stream_id}/detect"]["post"]["responses"] == responses
    headers = [p for p in spec["paths"]["/detect"]["post"]["parameters"] if p["in"] == "header"]
    assert [h["name"] for h in headers] == ["X-Stream-Id"]


def _b64(data: bytes) -> str:
    import base64

    return base64.b64encode(data).decode()
