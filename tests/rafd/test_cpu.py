"""The one CPU count (rafd.cpu.usable_cpus): the affinity mask capped by the cgroup's CPU quota, v2 or v1."""

from __future__ import annotations

import os

import rafd.cpu
from rafd.cpu import cgroup_cpu_limit, usable_cpus


def test_cgroup_v2_quota(tmp_path):
    cpu_max = tmp_path / "cpu.max"
    cpu_max.write_text("150000 100000\n")
    assert cgroup_cpu_limit(cpu_max, tmp_path / "none", tmp_path / "none") == 2
    cpu_max.write_text("50000 100000\n")
    assert cgroup_cpu_limit(cpu_max, tmp_path / "none", tmp_path / "none") == 1
    cpu_max.write_text("max 100000\n")
    assert cgroup_cpu_limit(cpu_max, tmp_path / "none", tmp_path / "none") is None
    cpu_max.write_text("garbage")
    assert cgroup_cpu_limit(cpu_max, tmp_path / "none", tmp_path / "none") is None


def test_cgroup_v1_quota(tmp_path):
    quota, period = tmp_path / "quota", tmp_path / "period"
    quota.write_text("300000\n")
    period.write_text("100000\n")
    assert cgroup_cpu_limit(tmp_path / "none", quota, period) == 3
    quota.write_text("-1\n")
    assert cgroup_cpu_limit(tmp_path / "none", quota, period) is None


def test_usable_cpus_is_the_affinity_mask_capped_by_the_quota(monkeypatch):
    affinity = len(os.sched_getaffinity(0))
    monkeypatch.setattr(rafd.cpu, "cgroup_cpu_limit", lambda: None)
    assert usable_cpus() == affinity
    monkeypatch.setattr(rafd.cpu, "cgroup_cpu_limit", lambda: 1)
    assert usable_cpus() == 1
    monkeypatch.setattr(rafd.cpu, "cgroup_cpu_limit", lambda: affinity + 8)
    assert usable_cpus() == affinity
