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


def test_far_threshold_is_carried_into_the_onnx_metadata_and_read_back(tmp_path):
    from rafd.model.checkpoint import load_checkpoint, save_checkpoint
    from rafd.protocol import OperatingThreshold, operating_threshold

    checkpoint = make_checkpoint(tmp_path / "model.pt", small_config(2))
    model, cfg, meta = load_checkpoint(checkpoint)
    far = {"from_m": 50.0, "threshold": 0.5}
    save_checkpoint(checkpoint, model, cfg, meta | {"operating_threshold": 0.375, "operating_threshold_far": far})
    exported = export_onnx(checkpoint, tmp_path / "far.onnx", verify=False, log=lambda _: None)
    metadata = OnnxRunner(exported.path, threads=1).metadata
    assert operating_threshold(metadata) == OperatingThreshold(0.375, far=0.5, far_from_m=50.0)
    assert operating_threshold(metadata, override=0.25) == OperatingThreshold(0.25)  # a user's one threshold
