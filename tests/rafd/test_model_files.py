"""rafd.model_files: a checkpoint and an ONNX model told apart from their first bytes, and the messages that say so."""

from __future__ import annotations

from rafd.assets import default_checkpoint, default_onnx
from rafd.model_files import checkpoint_given_for_onnx, file_kind, onnx_given_for_checkpoint


def test_the_shipped_files_are_told_apart(tmp_path):
    assert file_kind(default_checkpoint()) == "checkpoint"
    assert file_kind(default_onnx()) == "onnx"
    other = tmp_path / "notes.txt"
    other.write_text("hello")
    assert file_kind(other) == "unknown" and file_kind(tmp_path / "missing") == "unknown"
    assert "is an ONNX model, not a checkpoint" in onnx_given_for_checkpoint(default_onnx())
    assert onnx_given_for_checkpoint(default_checkpoint()) is None
    assert "is a PyTorch checkpoint, not an ONNX model" in checkpoint_given_for_onnx(default_checkpoint())
    assert checkpoint_given_for_onnx(default_onnx()) is None and checkpoint_given_for_onnx(other) is None
