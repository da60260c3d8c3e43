"""rafd.eval.velocity_truth: the simulator's velocities read back by frame number; real labels' velocities from
ego-compensated differences."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from rafd.eval.velocity_truth import label_velocities, simulated_velocities


def test_simulated_velocities_are_read_by_frame_number(tmp_path: Path):
    (tmp_path / "annotations").mkdir()
    entries = [{"id": 4, "velocities": [[1.0, 2.0], [], [3.0, 4.0]]}, {"id": 9, "velocities": [[], [0.0, -1.0]]}]
    (tmp_path / "annotations" / "velocities.json").write_text(json.dumps(entries))
    truth = simulated_velocities(tmp_path, [2, 3])
    assert truth is not None
    assert list(truth[0]) == [9] and np.allclose(truth[0][9], [0.0, -1.0])
    assert list(truth[1]) == [4] and np.allclose(truth[1][4], [3.0, 4.0])
    assert simulated_velocities(tmp_path / "missing", [1]) is None


def test_label_velocities_remove_the_egos_motion():
    """A car driving 5 m/s north in the world, seen from an ego driving 10 m/s east and heading north-east."""
    times = np.array([0.0, 0.25, 0.5, 1.0])
    numbers = [1, 2, 3, 5]  # a gap before the last frame
    poses = np.array([[10.0 * t, 0.0, np.pi / 4] for t in times])
    car = [np.array([20.0, 5.0 * t]) for t in times]
    rotate = lambda yaw, v: np.array([[np.cos(yaw), np.sin(yaw)], [-np.sin(yaw), np.cos(yaw)]]) @ v  # noqa: E731
    boxes = [np.array([[*rotate(p[2], c - p[:2]), 1.8, 4.5, 0.0]]) for p, c in zip(poses, car)]
    truth = label_velocities(boxes, [np.array([7])] * 4, poses, times, numbers)
    expected = rotate(np.pi / 4, np.array([0.0, 5.0]))  # world north in the ego's axes
    for k in range(3):
        assert np.allclose(truth[k][7], expected)
    assert truth[3] == {}  # no neighbouring frame: no velocity
