"""Tracks' short trails for a stream's pictures: where each answered track was in the last scans, in this scan's
pixels (the answers' poses carry the world frame across scans)."""

from __future__ import annotations

from collections import OrderedDict, deque
from typing import Any

import numpy as np

from rafd.geometry import metres_to_pixels, rotation_matrix

TRAIL_SCANS = 12  # 3 s at 4 Hz


class Trails:
    """Call `add` with every answer, in order; `in_scan` gives the trails to draw on an answer's picture."""

    def __init__(self, length: int = TRAIL_SCANS, forget_after: int = 20) -> None:
        self.length, self.forget_after = length, forget_after
        self._world: OrderedDict[str, deque[np.ndarray]] = OrderedDict()  # track id -> world centres, oldest first
        self._seen: dict[str, int] = {}
        self._answers = 0

    def add(self, answer: dict[str, Any]) -> None:
        pose = np.array([answer["pose"][k] for k in ("x", "y", "yaw")], np.float64)
        self._answers += 1
        for box in answer["boxes"]:
            world = rotation_matrix(pose[2]) @ np.array([box["x"], box["y"]]) + pose[:2]
            self._world.setdefault(box["track_id"], deque(maxlen=self.length)).append(world)
            self._seen[box["track_id"]] = self._answers
        for track_id in [t for t, last in self._seen.items() if self._answers - last > self.forget_after]:
            del self._world[track_id], self._seen[track_id]

    def in_scan(self, answer: dict[str, Any], resolution: float) -> dict[str, np.ndarray]:
        """Track id -> [P, 2] its centres so far in this answer's posted pixels (its scan's ego frame)."""
        pose = np.array([answer["pose"][k] for k in ("x", "y", "yaw")], np.float64)
        posted = int(answer["input"]["posted_size"])
        trails = {}
        for track_id, centres in self._world.items():
            ego = (np.stack(centres) - pose[:2]) @ rotation_matrix(pose[2])  # R^T (world - t), row vectors
            trails[track_id] = metres_to_pixels(ego, posted, resolution)
        return trails
