"""A model using the speed options (flow at stride 8, 4 x 4-cell enhancement windows) exports and streams through
onnxruntime like PyTorch's padded windows, warm-up frames included."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from export.verify import Report, random_sequence, verify_stream
from rafd.runtime import OnnxRunner
from tests.utils.export_testing import make_checkpoint, small_config

torch = pytest.importorskip("torch")


def test_options_model_matches_onnxruntime(tmp_path) -> None:
    from export.onnx_export import export_onnx
    from rafd.model.checkpoint import load_checkpoint

    base = small_config(4)
    cfg = base.replace(
        flow=dataclasses.replace(base.flow, stride=8), enhance=dataclasses.replace(base.enhance, window=4)
    )
    checkpoint = make_checkpoint(tmp_path / "options.pt", cfg)
    model, loaded, _ = load_checkpoint(checkpoint)
    assert loaded == cfg
    model = model.eval()
    path = export_onnx(checkpoint, tmp_path / "step.onnx", verify=False, log=lambda _: None).path
    step = OnnxRunner(path, threads=1)
    assert step.config == cfg
    frames, poses = random_sequence(cfg, 7, seed=8)
    report = Report()
    verify_stream(step, model, [(frames, poses)], report, "random")
    assert report.ok, "\n".join(report.lines())
    assert report.cases["random"] == 7
    assert report.diffs["random"]["flow"].max_abs < 1e-4 and report.diffs["random"]["boxes"].unmatched == 0
    # the flow output is on the detection grid (upsampled), as the service's contract says
    result, _ = step.step(step.new_state(), frames[:1], poses[:1])
    assert result.flow.shape == (1, 2, cfg.feature_size, cfg.feature_size)
    assert np.isfinite(result.flow).all()


def test_pre_norm_propagation_matches_onnxruntime(tmp_path) -> None:
    """Pre-norm propagation blocks (the shipped recipe's), with their zero-initialised branches made non-zero so
    the exported graph's attention and FFN paths are exercised, not skipped as an identity."""
    from export.onnx_export import export_onnx
    from rafd.model import build_model
    from rafd.model.checkpoint import load_checkpoint, save_checkpoint

    base = small_config(4)
    cfg = base.replace(propagation=dataclasses.replace(base.propagation, norm="pre"))
    torch.manual_seed(3)
    model = build_model(cfg).eval()
    with torch.no_grad():
        for parameter in model.propagation.parameters():
            parameter.add_(torch.randn_like(parameter) * 0.1)
    checkpoint = save_checkpoint(tmp_path / "pre.pt", model, cfg, meta={"purpose": "export tests"})
    model, loaded, _ = load_checkpoint(checkpoint)
    assert loaded.propagation.norm == "pre"
    path = export_onnx(checkpoint, tmp_path / "step.onnx", verify=False, log=lambda _: None).path
    frames, poses = random_sequence(cfg, 6, seed=4)
    report = Report()
    verify_stream(OnnxRunner(path, threads=1), model, [(frames, poses)], report, "random")
    assert report.ok, "\n".join(report.lines())
    assert report.diffs["random"]["boxes"].unmatched == 0
