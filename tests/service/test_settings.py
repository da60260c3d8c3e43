"""Settings: RAFD_* environment, CPU count from the affinity mask and the cgroup quota."""

from __future__ import annotations

import os

import pytest
from pydantic import ValidationError

from service import settings as settings_module
from service.settings import Settings, available_cpus, cgroup_cpu_limit, get_settings


def test_environment_variables_with_the_rafd_prefix(monkeypatch, tmp_path):
    monkeypatch.setenv("RAFD_MAX_STREAMS", "7")
    monkeypatch.setenv("RAFD_STREAM_TTL_S", "2.5")
    monkeypatch.setenv("RAFD_MODEL_PATH", str(tmp_path / "m.onnx"))
    monkeypatch.setenv("RAFD_SCORE_THRESHOLD", "0.45")
    monkeypatch.setenv("RAFD_BUFFER_LENGTH", "4")
    s = Settings()
    assert (s.max_streams, s.stream_ttl_s, s.score_threshold, s.buffer_length) == (7, 2.5, 0.45, 4)
    assert s.model_path == tmp_path / "m.onnx"


@pytest.mark.parametrize(
    "name,value",
    [("RAFD_MAX_STREAMS", "0"), ("RAFD_SCORE_THRESHOLD", "1.5"), ("RAFD_THREADS", "zero"), ("RAFD_STREAM_TTL_S", "-1")],
)
def test_invalid_environment_is_an_error_naming_the_field(monkeypatch, name, value):
    monkeypatch.setenv(name, value)
    with pytest.raises(ValidationError, match=name.removeprefix("RAFD_").lower()):
        Settings()


def test_get_settings_is_cached():
    get_settings.cache_clear()
    try:
        assert get_settings() is get_settings()
    finally:
        get_settings.cache_clear()


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


def test_threads_default_is_the_affinity_mask_capped_by_the_quota(monkeypatch):
    affinity = len(os.sched_getaffinity(0))
    monkeypatch.setattr(settings_module, "cgroup_cpu_limit", lambda: None)
    assert available_cpus() == affinity == Settings().threads
    monkeypatch.setattr(settings_module, "cgroup_cpu_limit", lambda: 1)
    assert available_cpus() == 1 == Settings().threads
    monkeypatch.setattr(settings_module, "cgroup_cpu_limit", lambda: affinity + 8)
    assert available_cpus() == affinity
