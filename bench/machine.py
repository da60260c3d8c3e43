"""What machine a figure was measured on: CPU model, its bf16 units and the cores this process may use."""

from __future__ import annotations

from rafd.cpu import BF16_UNITS, cpu_model_and_flags, has_units, usable_cpus


def has_bf16_units() -> bool:
    """Whether the CPU computes bf16 natively (avx512_bf16 or AMX); elsewhere bf16 is emulated and slow."""
    return has_units(BF16_UNITS)


def machine_description(threads: int) -> str:
    model, flags = cpu_model_and_flags()
    found: list[str] = [f for f in ("avx512_bf16", "amx_bf16", "amx_int8", "avx512_vnni") if f in flags]
    units = found or ["no bf16 units"]
    return f"{model} ({', '.join(units)}), {usable_cpus()} usable cores, {threads} threads"
