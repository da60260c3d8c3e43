"""The CPU this process runs on: how many of its CPUs this process may use (usable_cpus, the one count every thread
and worker default reads), and from /proc/cpuinfo its model name and feature flags, and the units that make a
reduced precision worth serving (bf16: avx512_bf16 or AMX; int8: VNNI or AMX), used by the runtime's choice of
precision and by the benchmarks' machine lines."""

from __future__ import annotations

import math
import os
from pathlib import Path

CGROUP_V2_CPU_MAX = Path("/sys/fs/cgroup/cpu.max")
CGROUP_V1_QUOTA = Path("/sys/fs/cgroup/cpu/cpu.cfs_quota_us")
CGROUP_V1_PERIOD = Path("/sys/fs/cgroup/cpu/cpu.cfs_period_us")

BF16_UNITS = ("avx512_bf16", "amx_bf16")
# int8 dot products in hardware: AVX-512 VNNI (Cascade Lake, Zen 4), AVX-VNNI (Alder Lake), AMX (Sapphire Rapids).
# Without them (AVX2 only: Zen 2) int8 convolutions run through 16-bit multiply-adds and gain little or nothing.
INT8_UNITS = ("avx512_vnni", "avx_vnni", "amx_int8")


def usable_cpus() -> int:
    """CPUs this process may use: its affinity mask (a container's cpuset; os.cpu_count() counts the host's), capped by
    the cgroup's CPU quota (a container's --cpus, which the mask does not show)."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cpus = os.cpu_count() or 1
    limit = cgroup_cpu_limit()
    return max(1, min(cpus, limit) if limit else cpus)


def cgroup_cpu_limit(
    cpu_max: Path = CGROUP_V2_CPU_MAX, v1_quota: Path = CGROUP_V1_QUOTA, v1_period: Path = CGROUP_V1_PERIOD
) -> int | None:
    """Whole CPUs allowed by the cgroup's CFS quota (v2 cpu.max, else v1 cfs_quota_us / cfs_period_us; rounded up),
    None when unlimited or unknown."""
    try:
        if cpu_max.is_file():
            quota, period = cpu_max.read_text().split()[:2]
            if quota == "max":
                return None
            return max(1, math.ceil(int(quota) / int(period)))
        if v1_quota.is_file() and v1_period.is_file():
            quota_us = int(v1_quota.read_text())
            if quota_us <= 0:  # -1 = unlimited
                return None
            return max(1, math.ceil(quota_us / int(v1_period.read_text())))
    except (OSError, ValueError):
        return None  # unreadable or malformed: the affinity mask alone
    return None


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
