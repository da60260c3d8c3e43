"""Test helpers: small RaFD checkpoints with random weights and their ONNX exports."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest

from rafd.config import HeadConfig, RaFDConfig

torch = pytest.importorskip("torch")
pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")


def small_config(num_frames: int) -> RaFDConfig:
    """The tiny network at 64 px (16 x 16 cells). K = 8: a random-weight heatmap has more local maxima than
    queries, so every query is a real peak (the non-peak fill of top-K is an arbitrary tie, see the report)."""
    return RaFDConfig.tiny(
        input_size=64, num_frames=num_frames, head=HeadConfig(num_queries=8, decoder_layers=1, num_points=4)
    )


def make_checkpoint(path: Path, cfg: RaFDConfig, seed: int = 0) -> Path:
    from rafd.model import build_model
    from rafd.model.checkpoint import save_checkpoint

    torch.manual_seed(seed)
    save_checkpoint(path, build_model(cfg).eval(), cfg, meta={"purpose": "export tests"})
    return path


@dataclass
class Exported:
    cfg: RaFDConfig
    checkpoint: Path
    model: torch.nn.Module  # loaded back from the checkpoint: the reference
    path: Path  # the ONNX step graph
    result: object  # export.onnx_export.ExportResult


def export_step(root: Path, num_frames: int, batch: str = "dynamic") -> Exported:
    from export.onnx_export import export_onnx
    from rafd.model.checkpoint import load_checkpoint

    cfg = small_config(num_frames)
    checkpoint = make_checkpoint(root / "model.pt", cfg)
    model, loaded_cfg, _ = load_checkpoint(checkpoint)
    assert loaded_cfg == cfg
    result = export_onnx(checkpoint, root / "step.onnx", batch=batch, verify=False, log=lambda _: None)
    return Exported(cfg, checkpoint, model.eval(), result.path, result)
