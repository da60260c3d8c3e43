"""Service test fixtures: an app around the FakeRunner, entered as a context manager (runs the lifespan)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.settings import Settings
from tests.utils.fake_runner import FakeRunner
from tests.utils.service_testing import FakeOdometry, wait_ready


@pytest.fixture
def settings() -> Settings:
    return Settings(
        threads=1, max_streams=64, stream_ttl_s=300.0, max_request_bytes=4 * 1024 * 1024, score_threshold=0.3
    )


@pytest.fixture
def runner() -> FakeRunner:
    return FakeRunner()


@pytest.fixture
def odometry() -> FakeOdometry:
    return FakeOdometry()


@pytest.fixture
def client(settings: Settings, runner: FakeRunner, odometry: FakeOdometry) -> Iterator[TestClient]:
    with TestClient(create_app(settings, runner=runner, odometry=odometry)) as test_client:
        wait_ready(test_client)
        yield test_client
