"""Settings: RAFD_* environment; threads from the one CPU count (rafd.cpu)."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from service.settings import Settings, get_settings


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


def test_threads_and_concurrent_runs_default_to_the_usable_cpus(monkeypatch):
    """The one CPU count (rafd.cpu.usable_cpus: the affinity mask capped by the cgroup quota)."""
    import rafd.cpu

    monkeypatch.setattr(rafd.cpu, "cgroup_cpu_limit", lambda: 1)
    assert Settings().threads == Settings().concurrent_runs == 1
