"""Why the service serves what it serves: the precisions this CPU runs, what the model's gate records allow, and the
one sentence `rafd serve` logs and GET /model reports (the fallback to fp32 names `rafd gate`)."""

from __future__ import annotations

import json

import pytest

from rafd.model_files import file_sha256
from rafd.runtime import create_runner, runners
from rafd.runtime.runners import gate_record, precision_choice

ALL = [("onnxruntime", "fp32"), ("openvino", "bf16"), ("openvino", "fp32")]
FP32_ONLY = [("onnxruntime", "fp32"), ("openvino", "fp32")]


def _record(verdict: str, frames: int = 699, detections: int = 1909, **made: str) -> dict[str, str]:
    pooled = {"frames": frames, "reference_detections": detections, "candidate_detections": detections}
    figures = {"candidate": "openvino/bf16", "reference": "onnxruntime/fp32", "figures": {"all": pooled}, **made}
    return {"gate_bf16": verdict, "gate_bf16_figures": json.dumps(figures)}


def test_gate_records_are_read_as_pass_fail_too_little_or_none():
    assert gate_record({}, "bf16") == "none"
    assert gate_record(_record("fail"), "bf16") == "fail"
    assert gate_record(_record("pass"), "bf16") == "pass"
    assert gate_record(_record("pass", frames=20), "bf16") == "pass on too little evidence"


def test_bf16_capable_without_a_record_serves_fp32_and_says_run_rafd_gate():
    choice = precision_choice("m.onnx", {}, ("auto", "auto"), ("openvino", "fp32"), {}, ALL)
    assert choice["cpu_precisions"] == ["fp32", "bf16"]
    assert choice["gate_records"] == {"bf16": "none", "int8": "none"} and choice["allowed_precisions"] == ["fp32"]
    assert choice["reason"] == (
        "bf16 capable, no gate record for this model: serving openvino/fp32; run `rafd gate m.onnx`"
    )


def test_a_failed_record_names_where_it_was_made_and_asks_for_no_new_gate():
    metadata = _record("fail", cpu="Intel Xeon (amx_bf16)", date="2026-12-02")
    timed = {"onnxruntime/fp32": 37.5, "openvino/fp32": 29.8}
    choice = precision_choice("m.onnx", metadata, ("auto", "auto"), ("openvino", "fp32"), timed, ALL)
    assert choice["allowed_precisions"] == ["fp32"]
    assert choice["reason"] == (
        "bf16 capable, gate record fail (made on Intel Xeon (amx_bf16), 2026-12-02): serving openvino/fp32, "
        "the fastest timed at start-up (29.8 ms a run; onnxruntime/fp32 37.5 ms)"
    )


def test_a_passed_record_allows_bf16_and_the_timing_decides():
    choice = precision_choice(
        "m.onnx",
        _record("pass"),
        ("auto", "auto"),
        ("openvino", "bf16"),
        {"onnxruntime/fp32": 37.5, "openvino/bf16": 24.4, "openvino/fp32": 29.8},
        ALL,
    )
    assert choice["allowed_precisions"] == ["fp32", "bf16"]
    assert choice["reason"].startswith("bf16 capable, gate passed: serving openvino/bf16, the fastest timed")
    assert "rafd gate" not in choice["reason"]


def test_a_pass_on_too_little_is_not_allowed_and_asks_for_a_new_gate():
    choice = precision_choice("m.onnx", _record("pass", frames=9), ("auto", "auto"), ("openvino", "fp32"), {}, ALL)
    assert choice["allowed_precisions"] == ["fp32"]
    assert "gate record pass on too little evidence" in choice["reason"]
    assert choice["reason"].endswith("run `rafd gate m.onnx`")


def test_a_cpu_without_reduced_precision_says_so_whatever_the_record():
    choice = precision_choice("m.onnx", _record("pass"), ("auto", "auto"), ("openvino", "fp32"), {}, FP32_ONLY)
    assert choice["cpu_precisions"] == ["fp32"] and choice["allowed_precisions"] == ["fp32"]
    assert choice["gate_records"]["bf16"] == "pass"  # the record is reported even where it cannot be used
    assert choice["reason"].startswith("this CPU runs no reduced precision")


def test_an_explicit_precision_is_the_operators_and_says_when_ungated():
    forced = precision_choice("m.onnx", {}, ("openvino", "bf16"), ("openvino", "bf16"), {}, ALL)
    assert forced["reason"] == (
        "precision bf16 set by the operator, without a passed accuracy gate: serving openvino/bf16"
    )
    fp32 = precision_choice("m.onnx", {}, ("onnxruntime", "fp32"), ("onnxruntime", "fp32"), {}, ALL)
    assert fp32["reason"] == "precision fp32 set by the operator: serving onnxruntime/fp32"


def test_create_runner_reports_the_fallback_on_a_bf16_cpu(ungated_onnx, monkeypatch):
    """As on a bf16 CPU, whatever this one is (the choice of candidates is what is tested, not bf16 kernels)."""
    pytest.importorskip("openvino")
    monkeypatch.setattr(runners, "supported_choices", lambda: ALL)
    runner = create_runner(ungated_onnx, "auto", "auto", threads=1, timer=lambda r: 0.01)
    assert runner.precision == "fp32"
    assert runner.precision_choice["gate_records"] == {"bf16": "none", "int8": "none"}
    assert runner.precision_choice["reason"].startswith("bf16 capable, no gate record for this model: serving ")
    assert runner.precision_choice["reason"].endswith(f"; run `rafd gate {ungated_onnx}`")
    assert runner.describe()["precision_choice"] == runner.precision_choice


def test_create_runner_reports_a_cpu_without_bf16(gated_onnx, monkeypatch):
    monkeypatch.setattr(runners, "supported_choices", lambda: [("onnxruntime", "fp32")])
    runner = create_runner(gated_onnx, "auto", "auto", threads=1)
    assert (runner.runtime, runner.precision) == ("onnxruntime", "fp32")
    assert runner.precision_choice["gate_records"] == {"bf16": "pass", "int8": "none"}
    assert runner.precision_choice["allowed_precisions"] == ["fp32"]
    assert runner.precision_choice["reason"] == (
        "this CPU runs no reduced precision (bf16 needs the openvino package and avx512_bf16 or AMX, int8 VNNI or "
        "AMX): serving onnxruntime/fp32"
    )


# ---------------------------------------------------------------- int8 (the quantized MODEL.int8.onnx beside it)
def _int8_record(sha256: str, islands: tuple[str, ...] = ()) -> dict[str, str]:
    pooled = {"frames": 699, "reference_detections": 1909, "candidate_detections": 1909}
    figures = {"candidate": "openvino/int8", "figures": {"all": pooled}, "int8_sha256": sha256}
    if islands:
        figures["islands"] = list(islands)
    return {"gate_int8": "pass", "gate_int8_figures": json.dumps(figures)}


def test_int8_is_offered_only_on_a_cpu_with_int8_units(monkeypatch):
    pytest.importorskip("openvino")
    import rafd.cpu

    for flags, offered in (({"avx2"}, False), ({"avx2", "avx512_vnni"}, True), ({"amx_int8"}, True)):
        monkeypatch.setattr(rafd.cpu, "cpu_model_and_flags", lambda flags=flags: ("a CPU", frozenset(flags)))
        assert (("openvino", "int8") in runners.supported_choices()) is offered, flags


def test_a_passed_int8_record_serves_only_the_file_it_judged(tmp_path):
    model = tmp_path / "m.onnx"
    quantized = tmp_path / "m.int8.onnx"
    with_int8 = ALL + [("openvino", "int8")]
    missing = precision_choice(model, _int8_record("0" * 64), ("auto", "auto"), ("openvino", "fp32"), {}, with_int8)
    assert missing["allowed_precisions"] == ["fp32"]
    assert "int8 capable, gate passed but no quantized model m.int8.onnx beside it" in missing["reason"]
    quantized.write_bytes(b"the judged file")
    judged = file_sha256(quantized)
    allowed = precision_choice(model, _int8_record(judged), ("auto", "auto"), ("openvino", "int8"), {}, with_int8)
    assert allowed["allowed_precisions"] == ["fp32", "int8"] and "int8 capable, gate passed" in allowed["reason"]
    quantized.write_bytes(b"quantized again after the gate")
    replaced = precision_choice(model, _int8_record(judged), ("auto", "auto"), ("openvino", "fp32"), {}, with_int8)
    assert replaced["allowed_precisions"] == ["fp32"]
    assert "is not the file its int8 gate judged" in replaced["reason"]


def test_create_runner_does_not_consider_int8_without_its_judged_file(gated_onnx, monkeypatch, caplog):
    import logging

    pytest.importorskip("openvino")
    monkeypatch.setattr(runners, "supported_choices", lambda: [("onnxruntime", "fp32"), ("openvino", "int8")])
    monkeypatch.setattr(runners, "gate_passed", lambda metadata, precision: True)  # as if int8 had passed
    with caplog.at_level(logging.INFO, logger="rafd.runtime.runners"):
        runner = create_runner(gated_onnx, "auto", "auto", threads=1, timer=lambda r: 0.01)
    assert (runner.runtime, runner.precision) == ("onnxruntime", "fp32")
    assert "openvino/int8 not considered: no quantized model" in caplog.text


def test_int8_passed_with_float32_islands_says_so_where_it_serves_them(tmp_path):
    model = tmp_path / "m.onnx"
    quantized = tmp_path / "m.int8.onnx"
    quantized.write_bytes(b"the judged file, its stem left float32")
    record = _int8_record(file_sha256(quantized), ("/encoder/backbone/stem/", "/head/heatmap/net/"))
    with_int8 = ALL + [("openvino", "int8")]
    served = precision_choice(model, record, ("auto", "auto"), ("openvino", "int8"), {}, with_int8)
    islands = "float32 islands /encoder/backbone/stem/, /head/heatmap/net/"
    assert f"int8 capable, gate passed with {islands}" in served["reason"]
    assert served["reason"].endswith(f"serving openvino/int8 with {islands}")
    other = precision_choice(model, record, ("auto", "auto"), ("onnxruntime", "fp32"), {}, with_int8)
    assert ": serving onnxruntime/fp32;" in other["reason"]  # the islands belong to int8 only
