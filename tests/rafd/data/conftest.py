"""Simulated sequences shared by the DATA tests (small and quick: a few hundred ms each)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from rafd.sim import Difficulty
from rafd.sim.sequence import SimulatedSequence, run_simulation
from rafd.sim.writer import write_sequence


@pytest.fixture(scope="session")
def sim_truth_and_folder(tmp_path_factory: pytest.TempPathFactory) -> tuple[SimulatedSequence, Path]:
    """(in-memory simulation, its RADIATE-format folder): a busy drive (seed 31: 7 road users, all moving), 10 frames
    of 384 px, split train_good_weather. Exact labels (yaw along each road user's travel): the flow test reads body
    orientations from them."""
    truth = run_simulation(31, 10, "train_good_weather", 384, Difficulty(), name="sim_31_0", ambiguous=False)
    return truth, write_sequence(truth, tmp_path_factory.mktemp("data_sim") / "sim_31_0")


@pytest.fixture
def sim_copy(sim_truth_and_folder, tmp_path: Path) -> Path:
    """A private copy of the simulated folder that a test may damage."""
    return Path(shutil.copytree(sim_truth_and_folder[1], tmp_path / "sim_31_0"))
