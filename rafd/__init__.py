"""RaFD: flow-guided multi-frame object detection on scanning-radar BEV images.

`import rafd` stays torch-free: the config, geometry and decoding are numpy-only so the
service can use them. Torch-backed names (`build_model`, checkpoints) load on first access.
"""

from __future__ import annotations

from typing import Any

from rafd.config import RaFDConfig

# The package version, written only here: pyproject.toml reads it ([tool.setuptools.dynamic]).
__version__ = "0.1.0"
__all__ = ["RaFDConfig", "build_model", "save_checkpoint", "load_checkpoint", "__version__"]

_LAZY = {
    "build_model": "rafd.model",
    "save_checkpoint": "rafd.model.checkpoint",
    "load_checkpoint": "rafd.model.checkpoint",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'rafd' has no attribute {name!r}")
