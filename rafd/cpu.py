"""The CPU this process runs on, from /proc/cpuinfo: its model name and feature flags, and the units that make a
reduced precision worth serving (bf16: avx512_bf16 or AMX; int8: VNNI or AMX), used by the runtime's choice of
precision and by the benchmarks' machine lines."""

from __future__ import annotations

from pathlib import Path

BF16_UNITS = ("avx512_bf16", "amx_bf16")
# int8 dot products in hardware: AVX-512 VNNI (Cascade Lake, Zen 4), AVX-VNNI (Alder Lake), AMX (Sapphire Rapids).
# Without them (AVX2 only: Zen 2) int8 convolutions run through 16-bit multiply-adds and gain little or nothing.
INT8_UNITS = ("avx512_vnni", "avx_vnni", "amx_int8")


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


def has_units(units: tuple[str, ...]) -> bool:
    """Whether the CPU has any of `units` (feature flags, e.g. BF16_UNITS or INT8_UNITS)."""
    return any(unit in cpu_model_and_flags()[1] for unit in units)
