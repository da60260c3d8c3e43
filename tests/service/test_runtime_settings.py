"""The runtime and precision settings: validated, applied when the model loads, and reported in /model and in
every /detect answer's `model` field."""

from __future__ import annotations

import numpy as np
import pytest
from fastapi.testclient import TestClient
from pydantic import ValidationError

from service.app import create_app
from service.settings import Settings
from tests.utils.service_testing import detect_json, wait_ready


def test_runtime_and_precision_from_the_environment(monkeypatch):
    monkeypatch.setenv("RAFD_RUNTIME", "openvino")
    monkeypatch.setenv("RAFD_PRECISION", "bf16")
    assert (Settings().runtime, Settings().precision) == ("openvino", "bf16")
    assert (Settings.model_fields["runtime"].default, Settings.model_fields["precision"].default) == ("auto", "auto")


def test_concurrent_runs_default_to_one_per_cpu(monkeypatch):
    from rafd.cpu import usable_cpus

    assert Settings().threads == Settings().concurrent_runs == usable_cpus()
    monkeypatch.setenv("RAFD_CONCURRENT_RUNS", "1")
    assert Settings().concurrent_runs == 1


@pytest.mark.parametrize(
    "name,value", [("RAFD_RUNTIME", "tensorrt"), ("RAFD_PRECISION", "int4"), ("RAFD_CONCURRENT_RUNS", "0")]
)
def test_unknown_runtime_or_precision_is_refused(monkeypatch, name, value):
    monkeypatch.setenv(name, value)
    with pytest.raises(ValidationError, match=name.removeprefix("RAFD_").lower()):
        Settings()


@pytest.mark.parametrize("runtime", ["onnxruntime", "openvino"])
def test_the_served_runtime_is_reported(runtime):
    if runtime == "openvino":
        pytest.importorskip("openvino")
    from rafd.assets import default_onnx

    settings = Settings(threads=2, concurrent_runs=2, runtime=runtime, precision="fp32", model_path=default_onnx())
    with TestClient(create_app(settings)) as client:
        wait_ready(client, timeout=60.0)
        served = client.get("/model").json()["runtime"]
        assert (served["runtime"], served["precision"], served["threads"]) == (runtime, "fp32", 2)
        assert (served["concurrent_runs"], served["threads_per_concurrent_run"]) == (2, 1)
        size = client.get("/model").json()["input_size"]
        answer = client.post("/detect", json=detect_json("s", 1.0, np.zeros((size, size), np.uint8), (0, 0, 0)))
        assert answer.status_code == 200, answer.text
        assert answer.json()["model"]["runtime"] == runtime and answer.json()["model"]["precision"] == "fp32"


def test_model_says_which_precisions_the_cpu_runs_and_why_it_serves_what_it_serves(tmp_path, caplog):
    """An ungated model on auto: fp32 served; on a bf16 CPU the reason names `rafd gate` (the fallback), elsewhere
    it says the CPU has no reduced precision. Logged at start-up and reported in GET /model."""
    import logging

    onnx = pytest.importorskip("onnx")
    from rafd.assets import default_onnx
    from rafd.runtime import supported_choices

    proto = onnx.load(str(default_onnx()))
    kept = [(p.key, p.value) for p in proto.metadata_props if not p.key.startswith("gate_")]
    del proto.metadata_props[:]
    for key, value in kept:
        proto.metadata_props.add(key=key, value=value)
    model = tmp_path / "ungated.onnx"
    onnx.save(proto, str(model))
    settings = Settings(threads=1, concurrent_runs=1, runtime="auto", precision="auto", model_path=model)
    with caplog.at_level(logging.INFO, logger="service.loading"), TestClient(create_app(settings)) as client:
        wait_ready(client, timeout=60.0)
        served = client.get("/model").json()["runtime"]
    choice = served["precision_choice"]
    assert served["precision"] == "fp32" and choice["allowed_precisions"] == ["fp32"]
    assert choice["gate_records"] == {"bf16": "none", "int8": "none"}
    precisions = sorted({p for _, p in supported_choices()}, key=["fp32", "bf16", "int8"].index)
    if ("openvino", "bf16") in supported_choices():
        assert choice["cpu_precisions"] == precisions
        assert choice["reason"].startswith("bf16 capable, no gate record for this model")  # int8's after, if any
        assert f": serving {served['runtime']}/fp32" in choice["reason"]
        assert choice["reason"].endswith(f"; run `rafd gate {model}`")
    else:
        assert choice["cpu_precisions"] == ["fp32"]
        assert choice["reason"].startswith("this CPU runs no reduced precision")
    assert f"precision: {choice['reason']}" in caplog.text


def test_bf16_with_float32_islands_is_served_and_named(tmp_path):
    """A model whose bf16 gate passed with float32 islands: `auto` may pick them, `bf16` serves them, and GET /model
    names the islands (where the CPU runs bf16)."""
    pytest.importorskip("openvino")
    onnx = pytest.importorskip("onnx")
    from rafd.assets import default_onnx
    from rafd.runtime.openvino_backend import openvino_supports_bf16
    from tests.utils.islands_model import make_islands_model

    if not openvino_supports_bf16():
        pytest.skip("this CPU has no bf16 (avx512_bf16 or AMX): the islands cannot be served here")
    proto = onnx.load(str(default_onnx()))
    kept = [(p.key, p.value) for p in proto.metadata_props if not p.key.startswith("gate_")]
    del proto.metadata_props[:]
    for key, value in kept:
        proto.metadata_props.add(key=key, value=value)
    onnx.save(proto, str(tmp_path / "ungated.onnx"))
    model = make_islands_model(tmp_path / "ungated.onnx", tmp_path / "m.onnx", ("/head/",))
    settings = Settings(threads=1, runtime="openvino", precision="bf16", model_path=model)
    with TestClient(create_app(settings)) as client:
        wait_ready(client, timeout=60.0)
        served = client.get("/model").json()["runtime"]
        assert (served["precision"], served["float32_islands"]) == ("bf16", ["/head/"])
        assert served["precision_choice"]["reason"] == (
            "precision bf16 set by the operator: serving openvino/bf16 with float32 islands /head/"
        )
