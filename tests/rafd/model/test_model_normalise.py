"""rafd.model.normalise: the gain-robust first module, its ONNX export, and configs that predate it."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from rafd.config import RaFDConfig
from rafd.model import build_model


def test_local_contrast_cancels_gain_and_gamma_and_keeps_local_structure() -> None:
    from rafd.model.normalise import LocalContrast

    generator = torch.Generator().manual_seed(0)
    grey = torch.rand(1, 1, 64, 64, generator=generator) * 60 + 10  # grey levels 10..70
    grey[..., 20:26, 30:34] += 120  # a bright object
    norm = LocalContrast(15)
    base = norm(grey / 255)
    gained = norm(grey * 1.3 / 255)  # receiver gain (no pixel saturates)
    gamma = norm(255 * (grey / 255) ** 1.3 / 255)  # a gamma change: exact in log grey, log1p makes it approximate
    assert (base - gained).abs().max() < 0.08 and (base - gamma).abs().max() < 0.25
    assert base[..., 22, 31] > 1.5 and base.mean().abs() < 0.2  # the object stands out, the floor is centred
    raw = grey * 1.3 / 255 - grey / 255
    assert raw.abs().max() > 0.2  # without it the network would see the gain


def test_local_contrast_exports_and_matches_onnxruntime(tmp_path) -> None:
    import onnxruntime as ort

    from rafd.model.normalise import LocalContrast

    module = LocalContrast(47).eval()
    frames = torch.rand(1, 1, 96, 96)
    torch.onnx.export(
        module,
        (frames,),
        str(tmp_path / "n.onnx"),
        dynamo=False,
        opset_version=17,
        input_names=["x"],
        output_names=["y"],
    )
    session = ort.InferenceSession(str(tmp_path / "n.onnx"), providers=["CPUExecutionProvider"])
    np.testing.assert_allclose(session.run(None, {"x": frames.numpy()})[0], module(frames).numpy(), atol=2e-4)


def test_local_contrast_survives_a_runtime_that_computes_it_in_bf16(tmp_path) -> None:
    """OpenVINO's bf16 hint converts every op of the graph. The running-sum formulation this module had before lost
    the whole signal there (errors up to 56 on a unit-spread output); the centred box means keep it."""
    import pytest

    from rafd.model.normalise import LocalContrast
    from rafd.runtime.openvino_backend import openvino_supports_bf16

    if not openvino_supports_bf16():
        pytest.skip("needs openvino and a CPU with bf16 (avx512_bf16 or AMX)")
    import openvino as ov

    generator = torch.Generator().manual_seed(1)
    grey = 20 + 8 * torch.randn(1, 1, 256, 256, generator=generator).abs()  # a speckled floor of grey ~26
    grey[..., 100:110, 60:66] = 90  # a faint vehicle
    grey[..., 30:34, :] = 160  # a wall
    frames = (grey.clamp(0, 255).round() / 255).float()
    module = LocalContrast(47).eval()
    torch.onnx.export(
        module,
        (frames,),
        str(tmp_path / "n.onnx"),
        dynamo=False,
        opset_version=17,
        input_names=["x"],
        output_names=["y"],
    )
    compiled = ov.Core().compile_model(str(tmp_path / "n.onnx"), "CPU", {"INFERENCE_PRECISION_HINT": "bf16"})
    assert compiled.get_property("INFERENCE_PRECISION_HINT").get_type_name() == "bf16"
    error = np.abs(compiled({"x": frames.numpy()})[0] - module(frames).numpy())
    assert np.quantile(error, 0.99) < 0.1 and error.max() < 0.5, (np.quantile(error, 0.99), error.max())


def test_models_with_the_normalisation_build_and_a_config_without_it_is_refused() -> None:
    from rafd.config import InputConfig

    cfg = RaFDConfig.tiny(input_size=64, num_frames=2, input=InputConfig("local_contrast", 15))
    model = build_model(cfg)
    out = model(torch.rand(1, 2, 1, 64, 64), torch.zeros(1, 2, 3))
    assert torch.isfinite(out["scores"]).all()
    assert RaFDConfig.from_json(cfg.to_json()) == cfg
    legacy = json.loads(RaFDConfig.tiny().to_json())
    del legacy["input"]
    with pytest.raises(ValueError, match="missing"):
        RaFDConfig.from_dict(legacy)
