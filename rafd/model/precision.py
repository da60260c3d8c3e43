"""Numeric precision of training and inference: fp32, or bf16/fp16 autocast (fp16 with a gradient scaler).

bf16 autocast runs the convolutions, linear layers and attention matmuls in bfloat16 on CPUs with avx512_bf16 / AMX
and on GPUs, with float32 weights and optimizer state; the flow cost volume and its softmax stay float32
(rafd.model.flow), and the losses are computed in float32 (rafd.train.losses). fp16 needs a GradScaler and is offered
on CUDA only (CPU autocast has no fp16 convolutions worth having).
"""

from __future__ import annotations

import contextlib
from contextlib import AbstractContextManager as ContextManager

import torch

PRECISIONS = ("fp32", "bf16", "fp16")
_DTYPES = {"bf16": torch.bfloat16, "fp16": torch.float16}


def check_precision(precision: str, device: torch.device) -> None:
    """ValueError when `precision` is unknown or cannot run on `device`."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
    if precision == "fp16" and device.type != "cuda":
        raise ValueError("--precision fp16 needs a CUDA device (use bf16 on the CPU)")


def autocast(device: torch.device, precision: str) -> ContextManager:
    """The autocast context for a forward pass (a no-op for fp32)."""
    if precision == "fp32":
        return contextlib.nullcontext()
    return torch.autocast(device.type, dtype=_DTYPES[precision])


def grad_scaler(device: torch.device, precision: str) -> torch.amp.GradScaler:
    """A GradScaler that is active only for fp16 (bf16 has fp32's exponent range and needs none)."""
    return torch.amp.GradScaler(device.type, enabled=precision == "fp16")


def cpu_has_bf16() -> bool:
    """True when this CPU multiplies bf16 natively (avx512_bf16 or AMX-BF16): bf16 is then several times faster."""
    try:
        flags = open("/proc/cpuinfo").read()
    except OSError:
        return False
    return "avx512_bf16" in flags or "amx_bf16" in flags
