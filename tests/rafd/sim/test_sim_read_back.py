"""The DATA reader reads a simulated sequence unchanged (skips until rafd.data.read_sequence exists)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rafd.sim import Difficulty
from rafd.sim.sequence import run_simulation
from rafd.sim.writer import write_sequence


def test_read_sequence_returns_the_truth(tmp_path: Path) -> None:
    data = pytest.importorskip("rafd.data", reason="rafd.data (DATA helper) not available yet")
    if not hasattr(data, "read_sequence"):
        pytest.skip("rafd.data.read_sequence not available yet")
    truth = run_simulation(13, 5, "test", 1152, Difficulty(), name="sim_13_0")  # full RADIATE size
    sequence = data.read_sequence(write_sequence(truth, tmp_path / "sim_13_0"))
    assert sequence.name == "sim_13_0" and sequence.split == "test"
    assert [f.number for f in sequence.frames] == [1, 2, 3, 4, 5]
    np.testing.assert_allclose([f.timestamp for f in sequence.frames], truth.timestamps_ns / 1e9, atol=1e-6)
    np.testing.assert_allclose(sequence.poses, truth.poses, atol=1e-9)
    for index, frame in enumerate(sequence.frames):
        np.testing.assert_array_equal(sequence.load_image(index), truth.images[index])
        expected = {o.id: (o.class_name, o.boxes[index]) for o in truth.objects if np.isfinite(o.boxes[index, 0])}
        assert {obj.id for obj in frame.objects} == set(expected)
        for obj in frame.objects:
            assert obj.class_name == expected[obj.id][0]
            np.testing.assert_allclose(obj.box, expected[obj.id][1], atol=1e-6)
