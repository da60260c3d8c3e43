"""The device a forward pass runs on, from the name a user gives (training, evaluation, benchmarks alike)."""

from __future__ import annotations

import torch


def resolve_device(device: str) -> torch.device:
    """'cpu' | 'cuda' | 'cuda:N' | 'auto' -> a torch.device, with a clear error when CUDA is missing."""
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    try:
        resolved = torch.device(device)
    except RuntimeError as error:
        raise RuntimeError(f"unknown device {device!r} (use cpu, cuda, cuda:N or auto)") from error
    if resolved.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError(f"device {device!r} requested but CUDA is not available on this machine")
    if resolved.type not in ("cpu", "cuda"):
        raise RuntimeError(f"device {device!r} is not supported (use cpu, cuda, cuda:N or auto)")
    return resolved
