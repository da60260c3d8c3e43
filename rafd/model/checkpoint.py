"""RaFD checkpoints: weights + the exact config (+ free-form meta) in one torch file.

The file is a plain dict of tensors and strings so torch.load(weights_only=True) can read it without
unpickling arbitrary objects: {"state_dict", "config" (RaFDConfig JSON), "version", "meta" (JSON)}.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from torch import nn

from rafd.config import RaFDConfig
from rafd.model_files import onnx_given_for_checkpoint

if TYPE_CHECKING:  # the model code loads lazily
    from rafd.model import RaFD

CHECKPOINT_VERSION = "rafd-checkpoint/1"
_REQUIRED_KEYS = ("state_dict", "config", "version", "meta")


class CheckpointError(ValueError):
    """A checkpoint file that is missing, unreadable, not an RaFD checkpoint, or does not fit its config."""


def save_checkpoint(
    path: str | os.PathLike[str], model: nn.Module, cfg: RaFDConfig, meta: dict[str, Any] | None = None
) -> Path:
    """Write model weights + cfg + meta to `path` atomically (temp file in the same folder, then os.replace)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        # detached CPU copies: the file loads on any machine and never holds autograd state
        "state_dict": {k: v.detach().cpu().clone() for k, v in model.state_dict().items()},
        "config": cfg.to_json(),
        "version": CHECKPOINT_VERSION,
        "meta": json.dumps(meta or {}, sort_keys=True, default=str),
    }
    handle, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(handle, "wb") as stream:
            torch.save(payload, stream)
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(tmp_name, path)  # readers see the old file or the whole new one, never a partial write
    except BaseException:
        Path(tmp_name).unlink(missing_ok=True)
        raise
    return path


def read_checkpoint(
    path: str | os.PathLike[str], map_location: str | torch.device = "cpu"
) -> tuple[dict[str, torch.Tensor], RaFDConfig, dict[str, Any]]:
    """-> (state_dict, cfg, meta) without building a model; CheckpointError names the file on any problem."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    wrong_kind = onnx_given_for_checkpoint(path)
    if wrong_kind:
        raise CheckpointError(wrong_kind)
    try:
        payload = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as error:  # torch raises several types for truncated, foreign or garbage files
        # only the error's type: torch's message is advice for torch.load's callers (weights_only=False, "file an
        # issue"), not for someone who passed the wrong file
        raise CheckpointError(
            f"{path} is not a readable RaFD checkpoint (a truncated or foreign file: torch.load raised "
            f"{type(error).__name__}); pass the .pt file that `rafd train` writes"
        ) from error
    if not isinstance(payload, dict):
        raise CheckpointError(
            f"checkpoint {path} is not an RaFD checkpoint (holds a {type(payload).__name__}, not a dict)"
        )
    missing = [key for key in _REQUIRED_KEYS if key not in payload]
    if missing:
        raise CheckpointError(f"checkpoint {path} is not an RaFD checkpoint: missing keys {missing}")
    if payload["version"] != CHECKPOINT_VERSION:
        raise CheckpointError(f"checkpoint {path} has version {payload['version']!r}, expected {CHECKPOINT_VERSION!r}")
    state_dict = payload["state_dict"]
    if not isinstance(state_dict, dict) or not all(isinstance(v, torch.Tensor) for v in state_dict.values()):
        raise CheckpointError(f"checkpoint {path} has a malformed state_dict")
    try:
        cfg = RaFDConfig.from_json(payload["config"])
    except (TypeError, ValueError) as error:  # json.JSONDecodeError is a ValueError
        raise CheckpointError(f"checkpoint {path} holds an invalid config JSON: {error}") from error
    try:
        meta = json.loads(payload["meta"])
    except (TypeError, ValueError) as error:
        raise CheckpointError(f"checkpoint {path} holds invalid meta JSON: {error}") from error
    return state_dict, cfg, meta


def load_checkpoint(
    path: str | os.PathLike[str], map_location: str | torch.device = "cpu"
) -> tuple[RaFD, RaFDConfig, dict[str, Any]]:
    """-> (model rebuilt from the stored config, in eval mode, cfg, meta dict)."""
    from rafd.model import build_model

    state_dict, cfg, meta = read_checkpoint(path, map_location)
    model = build_model(cfg)
    try:
        model.load_state_dict(state_dict, strict=True)
    except RuntimeError as error:  # missing/unexpected keys or shape mismatches
        raise CheckpointError(f"checkpoint {path} does not fit its config (state_dict mismatch): {error}") from error
    model.to(map_location)
    model.eval()
    return model, cfg, meta
