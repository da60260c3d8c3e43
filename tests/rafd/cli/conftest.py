"""Fixtures for the CLI tests: a tiny simulated data root, a checkpoint trained on it for two steps, and a
loopback rafd-serve with the service tests' FakeRunner (for rafd-client)."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def sim_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from rafd.sim import simulate_dataset

    root = tmp_path_factory.mktemp("sim_cli")
    simulate_dataset(root, sequences=2, frames=5, seed=12, split="train", size=128)  # both drives hold vehicles
    return root


@pytest.fixture(scope="session")
def trained_checkpoint(sim_root: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    from rafd.cli.train import main

    out = tmp_path_factory.mktemp("ckpt") / "model.pt"
    argv = [
        "--data", str(sim_root), "--split", "train", "--config", "tiny", "--frames", "2", "--input-size", "64",
        "--out", str(out), "--epochs", "1", "--batch-size", "2", "--max-steps-per-epoch", "2", "--device", "cpu",
        "--no-progress",
    ]
    assert main(argv) == 0
    return out


@pytest.fixture
def service_url():
    """A real uvicorn server on loopback running the service with the FakeRunner and a fake odometry."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "service"))  # the service tests' helpers
    import httpx
    from fake_runner import FakeRunner
    from service_testing import FakeOdometry, serve_in_thread, wait_ready

    from service.app import create_app
    from service.settings import Settings

    with serve_in_thread(create_app(Settings(threads=1), runner=FakeRunner(), odometry=FakeOdometry())) as url:
        with httpx.Client(base_url=url) as http:
            wait_ready(http)
        yield url
