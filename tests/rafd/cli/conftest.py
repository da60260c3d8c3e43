"""Fixtures for the CLI tests: a tiny simulated data root and a checkpoint trained on it for two steps."""
from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def sim_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from rafd.sim import simulate_dataset

    root = tmp_path_factory.mktemp("sim_cli")
    simulate_dataset(root, sequences=2, frames=5, seed=11, split="train", size=128)
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
