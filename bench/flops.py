"""FLOP counts of a module's call and the machine's measured matmul peaks (PyTorch)."""

from __future__ import annotations

from typing import Any

from bench.machine import has_bf16_units
from bench.timing import time_calls


def matmul_peaks_gflops(threads: int, n: int = 2048, repeats: int = 5) -> dict[str, float]:
    """Measured n^3 matmul throughput (GFLOP/s, best of `repeats`) with `threads` torch threads: float32 always,
    bfloat16 only where the CPU has bf16 units (oneDNN: AMX / avx512_bf16). Elsewhere torch emulates bf16 about 40x
    slower than fp32 (a 2048^3 product took minutes on a 2-core Zen 2) and no runtime here uses it."""
    import torch

    previous = torch.get_num_threads()
    torch.set_num_threads(threads)
    dtypes = {"fp32": torch.float32} | ({"bf16": torch.bfloat16} if has_bf16_units() else {})
    peaks = {}
    try:
        for name, dtype in dtypes.items():
            a, b = torch.randn(n, n, dtype=dtype), torch.randn(n, n, dtype=dtype)

            def matmul(_: int, a: torch.Tensor = a, b: torch.Tensor = b) -> torch.Tensor:
                return torch.mm(a, b)

            samples = time_calls(matmul, repeats)
            peaks[name] = 2.0 * n**3 / min(samples) / 1e9
    finally:
        torch.set_num_threads(previous)
    return peaks


def count_flops(module: Any, *inputs: Any) -> float:
    """FLOPs of one call (matmul/conv/attention counted by torch's FlopCounterMode; grid_sample etc. not)."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    counter = FlopCounterMode(display=False)
    with torch.no_grad(), counter:
        module(*inputs)
    return float(counter.get_total_flops())
