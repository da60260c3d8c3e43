"""A tiny simulated data root shared by the training, evaluation and command-line tests (2 sequences, a few 128 px
frames)."""

from __future__ import annotations

from pathlib import Path

import pytest

from rafd.config import RaFDConfig


@pytest.fixture(scope="session")
def tiny_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from rafd.sim import simulate_dataset

    root = tmp_path_factory.mktemp("sim")
    simulate_dataset(root, sequences=2, frames=5, seed=12, split="train", size=128)  # both drives hold vehicles
    return root


@pytest.fixture(scope="session")
def tiny_cfg() -> RaFDConfig:
    """The tiny network at 64 px and 2 frames: every module runs, a step takes milliseconds."""
    return RaFDConfig.tiny(input_size=64, num_frames=2)
