"""The `cpu` recipe's network (convolutional enhancement, local cost volume, joint propagation) exports and streams
through onnxruntime like PyTorch's windows, with its zero-initialised branches made non-zero so the exported joint
attention and FFN are exercised rather than skipped as an identity."""

from __future__ import annotations

import dataclasses

import pytest

from export.verify import Report, random_sequence, verify_stream
from rafd.runtime import OnnxRunner
from tests.utils.export_testing import small_config

torch = pytest.importorskip("torch")


def cpu_like_config():  # noqa: ANN201 - RaFDConfig, imported lazily with torch
    base = small_config(4)
    return base.replace(
        enhance=dataclasses.replace(base.enhance, kind="conv", window=0),
        flow=dataclasses.replace(base.flow, num_cross_blocks=0, local_radius=2, channels=8),
        propagation=dataclasses.replace(base.propagation, mode="joint", num_blocks=1, num_points=2, norm="pre"),
    )


def test_cpu_network_matches_onnxruntime(tmp_path) -> None:
    from export.onnx_export import export_onnx
    from rafd.model import build_model
    from rafd.model.checkpoint import save_checkpoint

    cfg = cpu_like_config()
    torch.manual_seed(5)
    model = build_model(cfg).eval()
    with torch.no_grad():
        for parameter in model.parameters():
            if not parameter.abs().sum():
                parameter.normal_(0.0, 0.05)
    checkpoint = tmp_path / "cpu.pt"
    save_checkpoint(checkpoint, model, cfg)
    step_path = export_onnx(checkpoint, tmp_path / "step.onnx", verify=False, log=lambda _: None).path
    step = OnnxRunner(step_path, threads=1)
    assert step.config == cfg
    frames, poses = random_sequence(cfg, 6, seed=2)
    report = Report()
    verify_stream(step, model, [(frames, poses)], report, "random")
    assert report.ok, "\n".join(report.lines())
    assert report.diffs["random"]["flow"].max_abs < 1e-4 and report.diffs["random"]["boxes"].unmatched == 0


def test_cpu_recipe_is_the_reshaped_default() -> None:
    from rafd.train.recipes import recipe_model

    cpu, default = recipe_model("cpu"), recipe_model("default")
    assert (cpu.enhance.kind, cpu.flow.local_radius, cpu.propagation.mode) == ("conv", 3, "joint")
    assert (cpu.backbone, cpu.neck, cpu.head, cpu.input) == (
        default.backbone,
        default.neck,
        default.head,
        default.input,
    )
    assert recipe_model("paper").propagation.mode == "chain" and recipe_model("paper").flow.local_radius == 0
