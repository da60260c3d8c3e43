"""What machine a figure was measured on: CPU model, its bf16 units and the cores this process may use."""

from __future__ import annotations

import os
from pathlib import Path

BF16_UNITS = ("avx512_bf16", "amx_bf16")


def cpu_model_and_flags() -> tuple[str, frozenset[str]]:
    """(model name, feature flags) from /proc/cpuinfo; ("unknown CPU", {}) where it cannot be read."""
    model, flags = "unknown CPU", frozenset[str]()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name") and model == "unknown CPU":
                model = line.split(":", 1)[1].strip()
            if line.startswith("flags") and not flags:
                flags = frozenset(line.split(":", 1)[1].split())
    except OSError:
        pass
    return model, flags


def has_bf16_units() -> bool:
    """Whether the CPU computes bf16 natively (avx512_bf16 or AMX); elsewhere bf16 is emulated and slow."""
    return any(unit in cpu_model_and_flags()[1] for unit in BF16_UNITS)


def usable_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def machine_description(threads: int) -> str:
    model, flags = cpu_model_and_flags()
    found: list[str] = [f for f in ("avx512_bf16", "amx_bf16", "amx_int8", "avx512_vnni") if f in flags]
    units = found or ["no bf16 units"]
    return f"{model} ({', '.join(units)}), {usable_cores()} usable cores, {threads} threads"
