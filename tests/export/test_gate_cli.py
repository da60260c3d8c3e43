"""rafd gate: the verdicts recorded in an existing ONNX model without re-exporting (graph and metadata kept, a
precision's old record replaced), read back where the service reads them; the command on a real model."""

from __future__ import annotations

import json
import re
import shutil

import pytest

from export.gate import record_gates
from export.gate_options import GateThresholds
from export.gate_report import GateReport, SourceFigures
from rafd.runtime import OnnxRunner, supported_choices
from rafd.runtime.runners import gate_passed, gate_record

onnx = pytest.importorskip("onnx")


@pytest.fixture
def model_copy(tmp_path):
    from rafd.assets import default_onnx

    try:
        shipped = default_onnx()
    except FileNotFoundError as error:
        pytest.skip(f"the shipped model is not built: {error}")
    # any gate record the shipped file may carry is dropped: each test starts from an ungated model
    proto = onnx.load(str(shipped))
    kept = [(p.key, p.value) for p in proto.metadata_props if not p.key.startswith("gate_")]
    del proto.metadata_props[:]
    for key, value in kept:
        proto.metadata_props.add(key=key, value=value)
    path = tmp_path / "model.onnx"
    onnx.save(proto, str(path))
    return path


def _report(frames: int, detections: int, changed: int) -> GateReport:
    figures = SourceFigures(frames=frames, reference_detections=detections, candidate_detections=detections)
    figures.changed = changed
    figures.centre_shifts, figures.score_differences = [0.01] * (detections - changed), [0.001] * detections
    return GateReport("onnxruntime/fp32", "openvino/bf16", GateThresholds(), {"simulated": figures})


def test_a_recorded_pass_is_read_back_by_the_runtime_and_nothing_else_changes(model_copy):
    before = onnx.load(str(model_copy))
    entries = record_gates(model_copy, {"bf16": _report(699, 1909, 10)})
    assert entries["gate_bf16"] == "pass"
    after = onnx.load(str(model_copy))
    assert after.graph.SerializeToString() == before.graph.SerializeToString()  # not re-exported
    old = {p.key: p.value for p in before.metadata_props}
    new = {p.key: p.value for p in after.metadata_props}
    assert {k: v for k, v in new.items() if not k.startswith("gate_")} == old
    metadata = OnnxRunner(model_copy, threads=1).metadata
    assert gate_passed(metadata, "bf16") and gate_record(metadata, "bf16") == "pass"
    made = json.loads(metadata["gate_bf16_figures"])
    assert made["figures"]["simulated"]["frames"] == 699 and made["cpu"] and made["date"]


def test_a_new_record_replaces_the_old_one_in_place(model_copy):
    record_gates(model_copy, {"bf16": _report(699, 1909, 10)})
    assert gate_passed(OnnxRunner(model_copy, threads=1).metadata, "bf16")
    record_gates(model_copy, {"bf16": _report(699, 1909, 200)})  # 10% changed: FAIL
    keys = [p.key for p in onnx.load(str(model_copy)).metadata_props]
    assert keys.count("gate_bf16") == 1 and keys.count("gate_bf16_figures") == 1
    metadata = OnnxRunner(model_copy, threads=1).metadata
    assert gate_record(metadata, "bf16") == "fail" and not gate_passed(metadata, "bf16")
    assert not list(model_copy.parent.glob(".*.tmp"))  # the atomic write left nothing behind


def test_out_takes_the_judged_files_of_the_records_it_keeps(model_copy, tmp_path, monkeypatch):
    """A gate on a CPU without int8 re-gates bf16 only: with --out, the input's int8 record is kept and the int8
    file it names goes beside the output with it."""
    import export.gate
    from export.gate_cli import main
    from rafd.model_files import file_sha256, int8_model_path

    quantized = int8_model_path(model_copy)
    quantized.write_bytes(b"stand-in for the quantized graph")
    report = _report(699, 1909, 10)
    report.judged_sha256 = file_sha256(quantized)
    record_gates(model_copy, {"int8": report})
    monkeypatch.setattr(export.gate, "run_export_gates", lambda path, options, log: {"bf16": _report(699, 1909, 10)})
    out = tmp_path / "served" / "model.onnx"
    out.parent.mkdir()
    assert main([str(model_copy), "--out", str(out)]) == 0
    metadata = OnnxRunner(out, threads=1).metadata
    assert gate_passed(metadata, "bf16") and gate_passed(metadata, "int8")
    assert int8_model_path(out).read_bytes() == quantized.read_bytes()
    assert json.loads(metadata["gate_int8_figures"])["int8_sha256"] == file_sha256(int8_model_path(out))


def test_the_command_records_this_cpus_verdicts(model_copy, capsys, monkeypatch):
    """A short gate (5 windows): too little to judge, so FAIL where the CPU has a reduced precision; where it has
    none, nothing is written."""
    pytest.importorskip("torch")  # the simulated windows
    from export.gate_cli import main

    monkeypatch.delenv("RAFD_RADIATE_SAMPLE", raising=False)
    reduced = [p for _, p in supported_choices() if p != "fp32"]
    before = model_copy.read_bytes()
    short = ["--gate-sequences", "1", "--gate-sequence-frames", "8", "--threads", "1"]
    assert main([str(model_copy), *short, "--calibration-sequences", "1", "--calibration-frames", "8"]) == 0
    out = capsys.readouterr().out
    if not reduced:
        assert "nothing to gate" in out and "is unchanged" in out and model_copy.read_bytes() == before
        return
    metadata = OnnxRunner(model_copy, threads=1).metadata
    for precision in reduced:
        assert metadata[f"gate_{precision}"] == "fail" and "too little to judge" in out
        assert json.loads(metadata[f"gate_{precision}_figures"])["figures"]["simulated"]["frames"] == 8 - 3
    assert f"recorded in {model_copy}: " in out and "bf16 gate FAIL" in out
    if "int8" in reduced:  # calibrated as asked
        assert re.search(r"int8 calibration: \d+ steps of 1 simulated sequences", out)


def test_the_command_reports_the_islands_it_recorded_and_no_islands_turns_the_search_off(
    model_copy, capsys, monkeypatch
):
    import export.gate
    from export.gate_cli import main
    from export.islands import write_islands
    from rafd.model_files import islands_sha256

    seen = []

    def gates(onnx_path, options, log):
        seen.append(options.islands)
        report = _report(699, 1909, 10)
        report.islands = ("/head/",)
        report.islands_sha256 = islands_sha256(write_islands(onnx_path, report.islands))
        return {"bf16": report}

    monkeypatch.setattr(export.gate, "run_export_gates", gates)
    assert main([str(model_copy), "--no-islands"]) == 0 and main([str(model_copy)]) == 0
    assert seen == [False, True]
    assert "bf16 gate PASS with float32 islands /head/ (model.bf16-islands/)" in capsys.readouterr().out


def test_the_command_refuses_a_checkpoint_and_a_missing_file(tmp_path, capsys):
    from export.gate_cli import main
    from rafd.assets import default_checkpoint

    try:
        checkpoint = shutil.copy(default_checkpoint(), tmp_path / "model.pt")
    except FileNotFoundError as error:
        pytest.skip(f"the shipped checkpoint is not built: {error}")
    assert main([str(checkpoint)]) == 1
    assert "is a PyTorch checkpoint, not an ONNX model" in capsys.readouterr().err
    assert main([str(tmp_path / "absent.onnx")]) == 1
    assert "is not a file" in capsys.readouterr().err


def _int8_gate(content: bytes, interrupt: bool = False):
    """A stand-in for run_export_gates: quantizes (writes MODEL.int8.onnx beside the model it is given) and passes,
    or is interrupted (SIGTERM's SystemExit) after quantizing."""
    from rafd.model_files import file_sha256, int8_model_path

    def gates(onnx_path, options, log):
        int8_model_path(onnx_path).write_bytes(content)
        if interrupt:
            raise SystemExit(143)
        report = _report(699, 1909, 10)
        report.judged_sha256 = file_sha256(int8_model_path(onnx_path))
        return {"int8": report}

    return gates


def test_out_leaves_the_input_and_its_judged_files_untouched(model_copy, tmp_path, monkeypatch):
    """With --out the input model and the int8 file beside it (which its own record names) are never written: the
    gate quantizes into its own working copy, whose files go beside the output."""
    import export.gate
    from export.gate_cli import main
    from rafd.model_files import file_sha256, int8_model_path

    int8_model_path(model_copy).write_bytes(b"the input's judged int8 model")
    before = model_copy.read_bytes()
    monkeypatch.setattr(export.gate, "run_export_gates", _int8_gate(b"a new quantization"))
    out = tmp_path / "served" / "model.onnx"
    out.parent.mkdir()
    assert main([str(model_copy), "--out", str(out)]) == 0
    assert model_copy.read_bytes() == before
    assert int8_model_path(model_copy).read_bytes() == b"the input's judged int8 model"
    record = json.loads(OnnxRunner(out, threads=1).metadata["gate_int8_figures"])
    assert int8_model_path(out).read_bytes() == b"a new quantization"
    assert record["int8_sha256"] == file_sha256(int8_model_path(out))
    assert sorted(p.name for p in out.parent.iterdir()) == ["model.int8.onnx", "model.onnx"]


def test_an_interrupted_gate_leaves_what_was_stored(model_copy, monkeypatch):
    """Killed after quantizing (SIGTERM), in place: the model and its int8 file are as they were, and the working
    folder is gone."""
    import export.gate
    from export.gate_cli import main
    from rafd.model_files import int8_model_path

    int8_model_path(model_copy).write_bytes(b"the judged int8 model")
    before = model_copy.read_bytes()
    monkeypatch.setattr(export.gate, "run_export_gates", _int8_gate(b"half a gate", interrupt=True))
    with pytest.raises(SystemExit):
        main([str(model_copy)])
    assert model_copy.read_bytes() == before and int8_model_path(model_copy).read_bytes() == b"the judged int8 model"
    assert sorted(p.name for p in model_copy.parent.iterdir()) == ["model.int8.onnx", "model.onnx"]
