"""App-level behaviour: import without torch, readiness gating, model info, metrics, OpenAPI."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
from fastapi.testclient import TestClient

from service.app import create_app
from service.settings import Settings
from tests.utils.fake_runner import WARM_UP_RUNS, FakeRunner
from tests.utils.service_testing import blob_frame, detect_json, wait_ready


def test_service_imports_no_torch_and_loads_no_model():
    code = (
        "import sys, service.app, service.cli; from service.app import create_app; "
        "assert 'torch' not in sys.modules, 'torch imported'; "
        "assert not {'onnxruntime', 'openvino'} & set(sys.modules), 'a runtime imported at import'; "
        "print('ok')"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"


def test_a_whole_request_cycle_runs_with_torch_unimportable():
    """Blocks `import torch` outright, then serves frames: nothing on the request path needs torch."""
    code = f"""
import sys
sys.modules["torch"] = None  # any `import torch` now raises ImportError
sys.path.insert(0, {str(Path(__file__).resolve().parents[2])!r})  # the repository root: tests.utils
from tests.utils.fake_runner import FakeRunner
from tests.utils.service_testing import FakeOdometry, blob_frame, detect_json, wait_ready
from fastapi.testclient import TestClient
from service.app import create_app
from service.settings import Settings
with TestClient(create_app(Settings(threads=1), runner=FakeRunner(), odometry=FakeOdometry())) as client:
    wait_ready(client)
    for t in range(3):
        r = client.post("/detect", json=detect_json("s", float(t), blob_frame(128, [(8, 8, 255)])))
        assert r.status_code == 200, r.text
    assert client.get("/metrics").status_code == 200 and client.get("/model").status_code == 200
print("ok")
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().endswith("ok")


def test_ready_only_after_warm_up_and_detect_refused_before(settings):
    gate = threading.Event()
    runner = FakeRunner(gate=gate)
    with TestClient(create_app(settings, runner=runner)) as client:
        assert client.get("/health/live").status_code == 200
        not_ready = client.get("/health/ready")
        assert not_ready.status_code == 503
        assert not_ready.json()["error"]["code"] == "not_ready"
        refused = client.post("/detect", json=detect_json("s", 1.0, blob_frame(128, [])))
        assert refused.status_code == 503
        gate.set()
        wait_ready(client)
        assert runner.calls == WARM_UP_RUNS
        assert client.post("/detect", json=detect_json("s", 1.0, blob_frame(128, []), (0, 0, 0))).status_code == 200


def wait_load_error(client: TestClient) -> dict:
    for _ in range(500):
        body = client.get("/health/ready").json()
        if "failed" in body.get("error", {}).get("message", ""):
            return body
        time.sleep(0.01)
    raise AssertionError(f"no load error reported: {body}")


def test_load_failure_is_reported_by_readiness(tmp_path):
    missing = tmp_path / "nope.onnx"
    with TestClient(create_app(Settings(model_path=missing, threads=1))) as client:
        body = wait_load_error(client)
        assert client.get("/health/ready").status_code == 503
        assert "nope.onnx" in body["error"]["message"]
        assert client.get("/health/live").status_code == 200


def test_buffer_length_must_match_model(runner):
    settings = Settings(threads=1, buffer_length=runner.config.num_frames + 1)
    with TestClient(create_app(settings, runner=runner)) as client:
        body = wait_load_error(client)
        assert "RAFD_BUFFER_LENGTH" in body["error"]["message"]


def test_model_endpoint_reports_metadata_and_config(client, runner):
    body = client.get("/model").json()
    assert body["metadata"] == runner.metadata
    assert body["config"]["input_size"] == runner.config.input_size == body["input_size"]
    assert body["num_frames"] == runner.config.num_frames
    assert body["feature_size"] == runner.config.feature_size
    assert body["accepted_image_sizes"] == [128, 1152]
    assert np.isclose(body["cell_size_m"], runner.config.cell_size)


def test_metrics_count_requests_errors_and_streams(client):
    frame = blob_frame(128, [(8, 8, 255)])
    assert client.post("/detect", json=detect_json("m1", 1.0, frame)).status_code == 200
    assert client.post("/detect", json=detect_json("m1", 0.5, frame)).status_code == 409
    assert client.post("/detect", json=detect_json("m2", 1.0, frame)).status_code == 200
    text = client.get("/metrics").text
    assert 'rafd_requests_total{code="200",method="POST",route="/detect"} 2.0' in text
    assert 'rafd_request_errors_total{code="409",route="/detect"} 1.0' in text
    assert "rafd_active_streams 2.0" in text
    assert 'rafd_stream_evictions_total{reason="lru"} 0.0' in text
    assert 'rafd_request_duration_seconds_count{route="/detect"} 3.0' in text
    assert "rafd_frames_processed_total 2.0" in text


def test_two_apps_do_not_share_metrics(settings, runner):
    with (
        TestClient(create_app(settings, runner=runner)) as first,
        TestClient(create_app(settings, runner=FakeRunner())) as second,
    ):
        wait_ready(first)
        wait_ready(second)
        first.get("/health/live")
        assert 'route="/health/live"' in first.get("/metrics").text
        assert 'route="/health/live"' not in second.get("/metrics").text


def test_openapi_documents_both_detect_bodies(client):
    spec = client.get("/openapi.json").json()
    content = spec["paths"]["/detect"]["post"]["requestBody"]["content"]
    assert set(content) == {"application/json", "multipart/form-data"}
    assert "image" in content["multipart/form-data"]["schema"]["properties"]
    assert "/streams/{stream_id}" in spec["paths"]


def test_unknown_route_uses_the_error_shape(client):
    response = client.get("/nope")
    assert response.status_code == 404
    assert response.json()["error"]["code"] == "not_found"
