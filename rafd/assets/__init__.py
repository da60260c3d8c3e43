"""The default model shipped inside the package: its checkpoint and its streaming ONNX export.

How they were made (training command, data seeds, test figures) is recorded in CHANGELOG.md, docs/benchmark.md and in
`default_model.json` beside them.
"""

from __future__ import annotations

from pathlib import Path

ASSETS = Path(__file__).resolve().parent
DEFAULT_CHECKPOINT = ASSETS / "rafd_default.pt"
DEFAULT_ONNX = ASSETS / "rafd_default.onnx"


def _shipped(path: Path) -> Path:
    if not path.is_file():
        raise FileNotFoundError(f"the shipped model file {path} is missing from this installation")
    return path


def default_checkpoint() -> Path:
    """Path of the shipped PyTorch checkpoint (rafd.load_checkpoint reads it)."""
    return _shipped(DEFAULT_CHECKPOINT)


def default_onnx() -> Path:
    """Path of the shipped streaming ONNX model (what `rafd-serve` serves by default)."""
    return _shipped(DEFAULT_ONNX)
