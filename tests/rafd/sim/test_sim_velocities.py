"""The simulator's true ground velocities (annotations/velocities.json): exact from the trajectories, beside every
annotated box, consistent with the labels' own motion."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from rafd.data.poses import read_ego_poses
from rafd.geometry import radiate_to_box, rotation_matrix, transform_points
from rafd.sim import simulate_dataset
from rafd.sim.sequence import trajectory_velocity


def test_trajectory_velocity_is_the_slope_of_the_segment():
    times = np.array([0.0, 1.0, 2.0, 4.0])
    boxes = np.zeros((4, 5))
    boxes[:, 0] = [0.0, 2.0, 2.0, 6.0]
    boxes[:, 1] = [0.0, 1.0, 3.0, 3.0]
    assert np.allclose(trajectory_velocity(times, boxes, 0.5), [2.0, 1.0])
    assert np.allclose(trajectory_velocity(times, boxes, 1.5), [0.0, 2.0])
    assert np.allclose(trajectory_velocity(times, boxes, 3.0), [2.0, 0.0])
    assert np.allclose(trajectory_velocity(times, boxes, 9.0), [2.0, 0.0])  # beyond: the last segment


def centre(label: dict) -> np.ndarray:
    return radiate_to_box(label["position"], label["rotation"], 512)[:2]


def clear_of_the_seam(xy: np.ndarray) -> bool:
    """Away from the radar and from straight ahead (where a sweep starts and ends): there a label's moment within its
    sweep, and so its place, jumps from scan to scan, and differencing labels says little about the velocity."""
    return bool(np.hypot(*xy) > 8.0 and abs(np.arctan2(xy[0], xy[1])) > 0.5)


def test_velocities_sit_beside_every_annotated_box_and_match_the_labels_motion(tmp_path: Path):
    (folder,) = simulate_dataset(tmp_path, sequences=1, frames=8, seed=3, size=512, ambiguous=False, progress=False)
    labels = json.loads((folder / "annotations/annotations.json").read_text())
    annotations = {entry["id"]: entry["bboxes"] for entry in labels}
    truths = json.loads((folder / "annotations/velocities.json").read_text())
    velocities = {entry["id"]: entry["velocities"] for entry in truths}
    assert velocities.keys() == annotations.keys()
    read = read_ego_poses(folder / "ego_poses.csv")  # {frame number: (timestamp, pose)}
    stamps = np.array([read[n][0] for n in sorted(read)])
    poses = np.stack([read[n][1] for n in sorted(read)])
    checked = 0
    for track, boxes in annotations.items():
        assert [bool(b) for b in boxes] == [bool(v) for v in velocities[track]]
        for k in range(len(boxes) - 1):
            if not (boxes[k] and boxes[k + 1]) or not all(clear_of_the_seam(centre(boxes[j])) for j in (k, k + 1)):
                continue
            # the labels' world displacement over the interval against the mean of its end velocities
            ends = [transform_points(poses[j], centre(boxes[j])) for j in (k, k + 1)]
            moved = (ends[1] - ends[0]) / (stamps[k + 1] - stamps[k])
            world = [rotation_matrix(poses[j, 2]) @ np.array(velocities[track][j]) for j in (k, k + 1)]
            assert np.linalg.norm(moved - 0.5 * (world[0] + world[1])) < 1.0  # the sweep's timing blurs the labels
            checked += 1
    assert checked > 5
