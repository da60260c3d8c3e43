"""Fixtures for the CLI tests: a tiny simulated data root, a checkpoint trained on it for two steps, and a
loopback rafd-serve with the service tests' FakeRunner (for rafd-client)."""

from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def sim_root(tiny_root: Path) -> Path:
    """The shared tiny simulated root (tests/rafd/conftest.py): the commands read it, never write into it."""
    return tiny_root


@pytest.fixture(scope="session")
def trained_checkpoint(sim_root: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    from rafd.cli.train import main

    out = tmp_path_factory.mktemp("ckpt") / "model.pt"
    argv = [
        str(sim_root),
        "--split",
        "train",
        "--config",
        "tiny",
        "--out",
        str(out),
        "--quiet",
        "model.num_frames=2",
        "model.input_size=64",
        "train.epochs=1",
        "train.batch_size=2",
        "train.max_steps_per_epoch=2",
        "train.device=cpu",
    ]
    assert main(argv) == 0
    return out


@pytest.fixture
def service_url():
    """A real uvicorn server on loopback running the service with the FakeRunner and a fake odometry."""
    import httpx

    from service.app import create_app
    from service.settings import Settings
    from tests.utils.fake_runner import FakeRunner
    from tests.utils.service_testing import FakeOdometry, serve_in_thread, wait_ready

    with serve_in_thread(create_app(Settings(threads=1), runner=FakeRunner(), odometry=FakeOdometry())) as url:
        with httpx.Client(base_url=url) as http:
            wait_ready(http)
        yield url
