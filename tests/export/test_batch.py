"""`rafd-export --batch dynamic`: one graph run for several streams' steps answers as the streams do alone."""

from __future__ import annotations

import numpy as np
import pytest

from export.onnx_export import ExportError, export_onnx
from export.verify import Report, random_sequence, verify_batched
from rafd.runtime import OnnxRunner
from tests.utils.export_testing import make_checkpoint, small_config


@pytest.fixture(scope="module", params=[4, 1], ids=["T4", "T1"])
def batched(request, tmp_path_factory):
    root = tmp_path_factory.mktemp(f"batch{request.param}")
    checkpoint = make_checkpoint(root / "model.pt", small_config(request.param))
    logs: list[str] = []
    verify = request.param > 1  # the batched verification of T = 4 covers the code; T = 1 checks step_many below
    result = export_onnx(checkpoint, root / "step.onnx", batch="dynamic", verify=verify, log=logs.append)
    static = export_onnx(checkpoint, root / "static.onnx", verify=False, log=lambda _: None)
    return result, static, logs


def test_dynamic_export_is_batchable_and_recorded(batched):
    result, static, logs = batched
    assert result.metadata["batch"] == "dynamic" and static.metadata["batch"] == "static"
    assert OnnxRunner(result.path).batchable and not OnnxRunner(static.path).batchable
    if result.report is not None:
        assert "batched" in result.report.diffs and result.report.ok  # verify_export ran the batched streams
        assert any("batched" in line for line in logs)


def test_step_many_equals_steps_one_by_one(batched):
    result, static, _ = batched
    runner, alone = OnnxRunner(result.path), OnnxRunner(static.path)
    cfg = runner.config
    length = cfg.num_frames + 2
    sequences = [random_sequence(cfg, length, seed=seed) for seed in (10, 11, 12)]
    states = [runner.new_state() for _ in sequences]
    alone_states = [alone.new_state() for _ in sequences]
    for n in range(length):
        items = [(states[k], seq[0][n], seq[1][n]) for k, seq in enumerate(sequences)]
        together = runner.step_many(items)
        for k, (result_k, state_k) in enumerate(together):
            single, alone_states[k] = alone.step(alone_states[k], sequences[k][0][n], sequences[k][1][n])
            states[k] = state_k
            assert result_k.frames_used == single.frames_used == min(n + 1, cfg.num_frames)
            np.testing.assert_allclose(result_k.heatmap, single.heatmap, atol=1e-5)
            np.testing.assert_allclose(result_k.scores, single.scores, atol=1e-5)
            if single.flow is not None:
                np.testing.assert_allclose(result_k.flow, single.flow, atol=1e-5)


def test_batched_verification_catches_a_mixed_up_row(batched, monkeypatch):
    result, _, _ = batched
    runner = OnnxRunner(result.path)
    cfg = runner.config
    original = runner.run

    def swapped(feeds):  # a batcher bug: rows handed back to the wrong streams
        out = original(feeds)
        return {name: value[::-1].copy() for name, value in out.items()}

    monkeypatch.setattr(runner, "run", swapped)
    report = Report()
    sequences = [random_sequence(cfg, 3, seed=seed) for seed in (1, 2)]
    verify_batched(runner, _model(result), sequences, report)
    assert not report.ok


def _model(result):
    from rafd.model.checkpoint import load_checkpoint

    return load_checkpoint(result.path.with_name("model.pt"))[0].eval()


def test_dynamic_batch_needs_the_step_form(tmp_path):
    checkpoint = make_checkpoint(tmp_path / "model.pt", small_config(4))
    with pytest.raises(ExportError, match="step form"):
        export_onnx(checkpoint, tmp_path / "w.onnx", form="window", batch="dynamic", log=lambda _: None)
    with pytest.raises(ExportError, match="batch must be one of"):
        export_onnx(checkpoint, tmp_path / "w.onnx", batch="8", log=lambda _: None)
