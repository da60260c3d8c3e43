"""The accuracy gate: it passes an identical runtime, catches a degraded one check by check, runs on the shipped
model, and rafd-export --gate records its verdict where the runtime selection reads it."""

from __future__ import annotations

import json

import numpy as np
import pytest

from export.gate import gate_metadata
from export.gate_drives import simulated_sequences
from export.gate_options import DEFAULT_SEED, GateThresholds
from export.gate_run import gate_model, run_gate
from rafd.runtime import OnnxRunner, StepResult, supported_choices
from rafd.runtime.runners import gate_passed

pytest.importorskip("torch")


@pytest.fixture(scope="module")
def shipped_onnx():
    from rafd.assets import default_onnx

    try:
        return default_onnx()
    except FileNotFoundError as error:
        pytest.skip(f"the shipped model is not built: {error}")


class Degraded:
    """Wraps a runner and damages its outputs: shifted boxes, noisy scores, biased flow."""

    def __init__(self, runner: OnnxRunner, shift_m: float = 0.0, score_noise: float = 0.0, flow_bias_m: float = 0.0):
        self.runner, self.config = runner, runner.config
        self.runtime, self.precision = "degraded", "test"
        self.shift_m, self.score_noise, self.flow_bias_m = shift_m, score_noise, flow_bias_m
        self.rng = np.random.default_rng(0)

    def new_state(self):
        return self.runner.new_state()

    def step(self, state, frames, poses):
        result, state = self.runner.step(state, frames, poses)
        boxes = result.boxes.copy()
        boxes[..., 0] += self.shift_m
        scores = np.clip(result.scores + self.rng.normal(0.0, self.score_noise, result.scores.shape), 0.0, 1.0)
        flow = None if result.flow is None else result.flow + self.flow_bias_m
        return StepResult(result.heatmap, boxes, scores.astype(np.float32), flow, result.frames_used), state


def _sources(cfg, sequences=1, frames=12):
    return {"simulated": simulated_sequences(cfg, sequences, frames, DEFAULT_SEED)}


def _failed(report) -> set[str]:
    return {check for _, check, _, _, ok in report.checks() if not ok}


# the checks themselves on a short sample: the evidence minimums lowered (tested on their own below)
SMALL_SAMPLE = GateThresholds(min_frames=1, min_reference_detections=0)


def test_identical_runtime_passes_with_zero_differences(shipped_onnx):
    reference, same = OnnxRunner(shipped_onnx, threads=1), OnnxRunner(shipped_onnx, threads=1)
    report = run_gate(reference, same, _sources(reference.config), SMALL_SAMPLE)
    assert report.ok, "\n".join(report.lines())
    sim = report.sources["simulated"]
    assert sim.frames == 12 - reference.config.num_frames + 1  # every full window, warm-up frames excluded
    assert sim.changed == 0 and sim.centre_p99 == 0.0 and sim.score_p99 == 0.0 and sim.flow_difference() == 0.0
    assert sim.reference_map == sim.candidate_map and sim.reference_epe == sim.candidate_epe
    assert 0.0 <= sim.reference_map[0.3] <= 100.0 and np.isfinite(sim.reference_epe)


@pytest.mark.parametrize(
    "damage,expected",
    [
        ({"shift_m": 0.2}, {"matched centre shift p99 (m)"}),
        ({"score_noise": 0.05}, {"matched score difference p99"}),
        ({"flow_bias_m": 0.5}, {"|flow EPE difference| (m)"}),
        ({"shift_m": 2.0}, {"changed detections (fraction)"}),  # farther than a cell: every detection changed
    ],
)
def test_degraded_runtime_fails_the_matching_check(shipped_onnx, damage, expected):
    reference = OnnxRunner(shipped_onnx, threads=1)
    degraded = Degraded(OnnxRunner(shipped_onnx, threads=1), **damage)
    report = run_gate(reference, degraded, _sources(reference.config), SMALL_SAMPLE)
    assert not report.ok and expected <= _failed(report), "\n".join(report.lines())


def test_gate_runs_on_the_shipped_model_in_every_reduced_precision(shipped_onnx, radiate_sample_or_none, tmp_path):
    """A small sample (the full gate is rafd-export --gate): the figures exist and agree with the verdict. int8 is
    gated on a quantized copy (calibrated briefly: its verdict is not what is tested)."""
    import shutil

    from export.quantize import calibrate, quantize_model

    reduced = [c for c in supported_choices() if c[1] != "fp32"]
    if not reduced:
        pytest.skip("this CPU runs no reduced precision (openvino with avx512_bf16 or AMX, or int8 units)")
    model = shutil.copy(shipped_onnx, tmp_path / "shipped.onnx")
    if ("openvino", "int8") in reduced:
        quantize_model(model, calibration=calibrate(model, sequences=1, frames=8))
    for candidate in reduced:
        report = gate_model(model, candidate, sequences=1, frames=16, radiate=radiate_sample_or_none, threads=1)
        assert report.candidate == "/".join(candidate) and report.reference == "onnxruntime/fp32"
        figures = report.figures()
        assert figures["simulated"]["frames"] == 16 - 3
        assert {"reference_mAP@0.7", "candidate_mAP@0.7", "reference_epe_m", "candidate_epe_m"} <= set(
            figures["simulated"]
        )
        if radiate_sample_or_none is not None:
            assert figures["radiate"]["frames"] > 0 and "reference_mAP@0.3" not in figures["radiate"]
        assert report.ok == all(ok for *_, ok in report.checks())
        metadata = gate_metadata({candidate[1]: report})
        assert gate_passed(metadata, candidate[1]) == report.ok
        assert json.loads(metadata[f"gate_{candidate[1]}_figures"])["figures"] == figures


def test_the_gate_refuses_to_judge_too_little(shipped_onnx):
    """An identical runtime on 9 windows: every difference is zero, but 9 windows are too few to show anything."""
    from rafd.protocol import GATE_MIN_FRAMES, GATE_MIN_REFERENCE_DETECTIONS

    reference, same = OnnxRunner(shipped_onnx, threads=1), OnnxRunner(shipped_onnx, threads=1)
    report = run_gate(reference, same, _sources(reference.config))
    assert not report.ok
    assert _failed(report) == {"compared windows (at least)"} | (
        {"reference detections (at least)"}
        if report.pooled.reference_detections < GATE_MIN_REFERENCE_DETECTIONS
        else set()
    )
    assert report.too_little().startswith("too little to judge: compared windows 9 < 100")
    assert "FAIL (too little to judge" in report.lines()[0]
    assert (GATE_MIN_FRAMES, GATE_MIN_REFERENCE_DETECTIONS) == (100, 100)
    # nothing detected at all: FAIL, never PASS on 0 reference and 0 candidate detections
    nothing = GateThresholds(score_threshold=1.0, min_frames=1)
    report = run_gate(reference, same, _sources(reference.config), nothing)
    assert report.pooled.reference_detections == 0 and not report.ok
    assert _failed(report) == {"reference detections (at least)"}


def test_the_service_never_considers_a_precision_without_a_gate_passed_on_enough(shipped_onnx):
    def figures(frames, detections):
        pooled = {"frames": frames, "reference_detections": detections, "candidate_detections": detections}
        return json.dumps({"candidate": "openvino/bf16", "figures": {"simulated": pooled}})

    assert gate_passed({}, "fp32")
    assert not gate_passed({"gate_bf16": "pass"}, "bf16")  # a verdict without its figures
    assert not gate_passed({"gate_bf16": "pass", "gate_bf16_figures": figures(0, 0)}, "bf16")  # PASS on nothing
    assert not gate_passed({"gate_bf16": "pass", "gate_bf16_figures": figures(500, 40)}, "bf16")
    assert not gate_passed({"gate_bf16": "fail", "gate_bf16_figures": figures(700, 1900)}, "bf16")
    assert gate_passed({"gate_bf16": "pass", "gate_bf16_figures": figures(700, 1900)}, "bf16")


def test_thresholds_are_the_briefs(shipped_onnx):
    t = GateThresholds()
    assert (t.score_threshold, t.changed_fraction, t.centre_p99_m, t.score_p99, t.map_points, t.epe_m) == (
        0.3,
        0.02,
        0.05,
        0.02,
        0.5,
        0.01,
    )


def test_export_records_the_gate_verdict(tmp_path, capsys, monkeypatch):
    from export.cli import main
    from tests.utils.export_testing import make_checkpoint, small_config

    monkeypatch.delenv("RAFD_RADIATE_SAMPLE", raising=False)  # simulated frames only: keeps the test short
    reduced = [c for c in supported_choices() if c[1] != "fp32"]
    checkpoint = make_checkpoint(tmp_path / "model.pt", small_config(4))
    output = tmp_path / "gated.onnx"
    assert (
        main(
            [
                str(checkpoint),
                str(output),
                "--no-verify",
                "--gate",
                "--gate-sequences",
                "1",
                "--gate-sequence-frames",
                "8",
                "--calibration-sequences",
                "1",
                "--calibration-frames",
                "8",
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    metadata = OnnxRunner(output).metadata
    if not reduced:
        assert "nothing to gate" in out and not any(k.startswith("gate_") for k in metadata)
        return
    for _, precision in reduced:
        # 5 windows of an untrained model: too little to judge, so FAIL (it used to PASS on 0 detections)
        assert metadata[f"gate_{precision}"] == "fail"
        assert f"{precision} gate FAIL" in out and "too little to judge" in out
        assert json.loads(metadata[f"gate_{precision}_figures"])["figures"]["simulated"]["frames"] == 8 - 3


def test_kept_drives_are_simulated_once_and_judged_alike(shipped_onnx, monkeypatch):
    """A search gates many candidates on the same short drives: kept in `drives`, they are simulated once."""
    import export.gate_run

    simulated = []
    monkeypatch.setattr(
        export.gate_run, "simulated_sequences", lambda *args: simulated.append(args) or simulated_sequences(*args)
    )
    drives: dict = {}
    same = ("onnxruntime", "fp32")
    first = gate_model(shipped_onnx, same, sequences=1, frames=8, seed=7200, threads=1, drives=drives)
    second = gate_model(shipped_onnx, same, sequences=1, frames=8, seed=7200, threads=1, drives=drives)
    assert len(simulated) == 1 and list(drives) == [(1, 8, 7200)] and len(drives[(1, 8, 7200)][0]) == 8
    assert first.figures() == second.figures() and first.pooled.frames == 8 - 3
