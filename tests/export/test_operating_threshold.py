"""The checkpoint's operating threshold (rafd-eval --calibrate) travels into the ONNX metadata; none, none there."""

from __future__ import annotations

import pytest

from export.onnx_export import export_onnx
from rafd.runtime import OnnxRunner
from tests.utils.export_testing import make_checkpoint, small_config

torch = pytest.importorskip("torch")


def test_operating_threshold_is_carried_into_the_onnx_metadata(tmp_path):
    from rafd.model.checkpoint import load_checkpoint, save_checkpoint

    checkpoint = make_checkpoint(tmp_path / "model.pt", small_config(2))
    plain = export_onnx(checkpoint, tmp_path / "plain.onnx", verify=False, log=lambda _: None)
    assert "operating_threshold" not in OnnxRunner(plain.path, threads=1).metadata
    model, cfg, meta = load_checkpoint(checkpoint)
    save_checkpoint(checkpoint, model, cfg, meta | {"operating_threshold": 0.4375})
    calibrated = export_onnx(checkpoint, tmp_path / "calibrated.onnx", verify=False, log=lambda _: None)
    assert float(OnnxRunner(calibrated.path, threads=1).metadata["operating_threshold"]) == 0.4375
