"""True ground velocities of labelled objects, per frame and id, in each frame's ego axes (x right, y forward), m/s.

- Simulated drives: the simulator's own, exact from its trajectories (annotations/velocities.json, written by
  rafd.sim.writer.velocities_json).
- Real labels (RADIATE, Oxford): the ego-compensated difference of a labelled id's positions between consecutive
  scans, v_t = R(-yaw_t) (world_t - world_t-1) / (t_t - t_t-1), world = pose o centre; the first scan of an id
  takes the forward difference. It carries the labels' own noise (a box drawn 0.2 m off is 0.8 m/s at 4 Hz).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from rafd.data.folders import VELOCITIES_FILE
from rafd.geometry import rotation_matrix, transform_points

Truth = list[dict[int, np.ndarray]]  # per frame position in a sequence: {id: velocity [2] m/s}


def simulated_velocities(folder: Path, numbers: Sequence[int]) -> Truth | None:
    """The simulator's velocities of a sequence folder for its frames `numbers` (frame k+1 = entry k); None when
    the folder has no velocities file (not simulated, or simulated before it was written)."""
    path = Path(folder) / VELOCITIES_FILE
    if not path.is_file():
        return None
    entries = json.loads(path.read_text())
    truth: Truth = [{} for _ in numbers]
    for entry in entries:
        velocities = entry["velocities"]
        for position, number in enumerate(numbers):
            index = int(number) - 1
            if 0 <= index < len(velocities) and len(velocities[index]) == 2:
                truth[position][int(entry["id"])] = np.asarray(velocities[index], np.float64)
    return truth


def label_velocities(
    boxes: Sequence[np.ndarray],
    ids: Sequence[np.ndarray],
    poses: np.ndarray,
    timestamps: np.ndarray,
    numbers: Sequence[int],
) -> Truth:
    """Per frame position: {id: velocity} from the labels' positions (boxes [M, 5] ego frame and ids [M] per frame,
    world poses [N, 3], timestamps [N] s, frame numbers [N]): backward differences over consecutive frame numbers,
    forward for an id's first frame; an id seen in no neighbouring frame has none."""
    world = [
        {int(i): transform_points(poses[k], b[:2]) for i, b in zip(ids[k], np.asarray(boxes[k]).reshape(-1, 5))}
        for k in range(len(numbers))
    ]
    truth: Truth = [{} for _ in numbers]
    for k in range(len(numbers)):
        for track, here in world[k].items():
            for other in (k - 1, k + 1):
                if not 0 <= other < len(numbers) or abs(int(numbers[other]) - int(numbers[k])) != 1:
                    continue
                there = world[other].get(track)
                dt = float(timestamps[k] - timestamps[other])
                if there is None or dt == 0:
                    continue
                truth[k][track] = rotation_matrix(-poses[k][2]) @ ((here - there) / dt)
                break
    return truth
