"""`rafd-export --batch`: a graph with a free batch axis steps several views (a whole scan's tiles) in one run."""

from __future__ import annotations

import numpy as np
import pytest

from export.onnx_export import ExportError, export_onnx
from export.verify import Report, random_sequence, verify_stream
from rafd.runtime import OnnxRunner
from rafd.runtime.backend import DYNAMIC
from tests.utils.export_testing import make_checkpoint, small_config


@pytest.fixture(scope="module")
def exports(tmp_path_factory):
    root = tmp_path_factory.mktemp("batch")
    checkpoint = make_checkpoint(root / "model.pt", small_config(4))
    logs: list[str] = []
    dynamic = export_onnx(checkpoint, root / "step.onnx", log=logs.append)
    static = export_onnx(checkpoint, root / "static.onnx", batch="static", verify=False, log=lambda _: None)
    return dynamic, static, logs


def test_dynamic_export_is_batched_verified_and_recorded(exports):
    dynamic, static, logs = exports
    assert dynamic.metadata["batch"] == "dynamic" and static.metadata["batch"] == "static"
    assert OnnxRunner(dynamic.path).batch == DYNAMIC and OnnxRunner(static.path).batch == 1
    assert "batched" in dynamic.report.diffs and dynamic.report.ok  # verify_export ran two views as one batch
    assert any("batched" in line for line in logs)


def test_a_static_graph_steps_views_one_by_one_alike(exports):
    dynamic, static, _ = exports
    batched, alone = OnnxRunner(dynamic.path), OnnxRunner(static.path)
    cfg = batched.config
    views = [random_sequence(cfg, cfg.num_frames + 2, seed=seed) for seed in (10, 11, 12)]
    states = [batched.new_state(), alone.new_state()]
    for n in range(cfg.num_frames + 2):
        frames = np.stack([f[n] for f, _ in views])
        poses = np.stack([p[n] for _, p in views])
        together, states[0] = batched.step(states[0], frames, poses)
        one_by_one, states[1] = alone.step(states[1], frames, poses)
        assert together.frames_used == one_by_one.frames_used == min(n + 1, cfg.num_frames)
        np.testing.assert_allclose(together.heatmap, one_by_one.heatmap, atol=1e-5)
        np.testing.assert_allclose(together.flow, one_by_one.flow, atol=1e-5)


def test_batched_verification_catches_a_mixed_up_row(exports, monkeypatch):
    dynamic, _, _ = exports
    runner = OnnxRunner(dynamic.path)
    original = runner.run

    def swapped(feeds):  # rows handed back to the wrong views
        out = original(feeds)
        return {name: value[::-1].copy() for name, value in out.items()}

    monkeypatch.setattr(runner, "run", swapped)
    from rafd.model.checkpoint import load_checkpoint

    model = load_checkpoint(dynamic.path.with_name("model.pt"))[0].eval()
    report = Report()
    verify_stream(runner, model, [random_sequence(runner.config, 3, seed=s) for s in (1, 2)], report, "batched")
    assert not report.ok


def test_an_unknown_batch_mode_is_refused(tmp_path):
    checkpoint = make_checkpoint(tmp_path / "model.pt", small_config(4))
    with pytest.raises(ExportError, match="batch must be one of"):
        export_onnx(checkpoint, tmp_path / "w.onnx", batch="8", log=lambda _: None)
