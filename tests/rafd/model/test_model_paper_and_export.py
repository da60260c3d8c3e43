"""The paper-size network runs; the tiny one exports to ONNX (opset 17, static) and matches onnxruntime."""

from __future__ import annotations

import time
import warnings
from pathlib import Path

import numpy as np
import torch

from rafd.config import RaFDConfig
from rafd.model import build_model, count_parameters


def test_paper_config_builds_and_runs_one_forward() -> None:
    cfg = RaFDConfig.paper()
    model = build_model(cfg).eval()
    assert 20e6 < count_parameters(model) < 30e6  # ResNet-34 (21.3M) + neck, attention, flow and head
    frames, poses = torch.rand(1, 4, 1, 256, 256), torch.zeros(1, 4, 3)
    poses[0, :, 1] = torch.arange(4) * 1.5
    start = time.perf_counter()
    with torch.no_grad():
        out = model(frames, poses)
    elapsed = time.perf_counter() - start
    assert out["heatmap"].shape == (1, 1, 64, 64) and out["flow"].shape == (1, 3, 2, 64, 64)
    assert out["boxes"].shape == (1, 64, 5) and torch.isfinite(out["boxes"]).all()
    assert elapsed < 60, elapsed  # ~2 s on 2 idle cores; generous for a shared CI machine


class _Window(torch.nn.Module):
    def __init__(self, model: torch.nn.Module) -> None:
        super().__init__()
        self.model = model

    def forward(self, frames: torch.Tensor, poses: torch.Tensor) -> tuple[torch.Tensor, ...]:
        out = self.model(frames, poses)
        return out["heatmap"], out["flow"], out["boxes"], out["scores"]


def test_onnx_export_matches_torch(make_config, make_inputs, tmp_path: Path) -> None:
    import onnx
    import onnxruntime

    cfg = make_config(4)
    # the wrapper itself must be in eval mode too: the TorchScript exporter traces the top module's mode
    wrapper = _Window(build_model(cfg)).eval()
    frames, poses = make_inputs(cfg, 1)
    path = tmp_path / "window.onnx"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            wrapper,
            (frames, poses),
            str(path),
            opset_version=17,
            dynamo=False,
            input_names=["frames", "poses"],
            output_names=["heatmap", "flow", "boxes", "scores"],
        )
    graph = onnx.load(str(path))
    ops = {node.op_type for node in graph.graph.node}
    assert "GridSample" in ops and not ops & {"NonZero", "Loop", "If", "Compress"}, ops
    session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    heatmap, flow, boxes, scores = session.run(None, {"frames": frames.numpy(), "poses": poses.numpy()})
    with torch.no_grad():
        expected = wrapper(frames, poses)
    np.testing.assert_allclose(heatmap, expected[0].numpy(), atol=1e-4)
    np.testing.assert_allclose(flow, expected[1].numpy(), atol=1e-4)
    # top-K order can differ on exact ties; compare boxes as sets via their sorted scores
    np.testing.assert_allclose(np.sort(scores[0]), np.sort(expected[3][0].numpy()), atol=1e-4)
    assert boxes.shape == tuple(expected[2].shape)
