"""Road users (RADIATE classes, realistic sizes): moving traffic both ways, parked vehicles, pedestrians."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rafd.sim.road import LANE_WIDTH, Road, speed_profile

# class -> ((width range), (length range), radar brightness relative to a car)
CLASS_SHAPES: dict[str, tuple[tuple[float, float], tuple[float, float], float]] = {
    "car": ((1.7, 1.95), (4.0, 4.9), 1.0),
    "van": ((1.9, 2.2), (4.8, 6.0), 1.3),
    "truck": ((2.4, 2.6), (7.5, 12.0), 1.8),
    "bus": ((2.5, 2.6), (10.5, 12.5), 1.8),
    "motorbike": ((0.7, 0.9), (1.8, 2.3), 0.55),
    "bicycle": ((0.5, 0.7), (1.6, 1.9), 0.35),
    "pedestrian": ((0.5, 0.7), (0.5, 0.7), 0.2),
    "group_of_pedestrians": ((1.5, 3.0), (1.5, 3.0), 0.3),
}
TRAFFIC_MIX = {"car": 0.62, "van": 0.15, "truck": 0.07, "bus": 0.06, "motorbike": 0.1}
PARKED_MIX = {"car": 0.8, "van": 0.2}
EGO_LENGTH = 4.7


@dataclass(frozen=True)
class Agent:
    """One road user; `s`/`offset` per frame along the road, `direction` -1 for oncoming."""

    id: int
    class_name: str
    width: float
    length: float
    brightness: float
    s: np.ndarray  # [T]
    offset: np.ndarray  # [T]
    direction: int

    def world_boxes(self, road: Road) -> np.ndarray:
        """[T, 5] world boxes (x, y, width, length, yaw), length along the direction of travel."""
        centres, heading = road.frame_at(self.s, self.offset)
        travel = heading + (0.0 if self.direction > 0 else np.pi)
        yaw = (travel - np.pi / 2.0 + np.pi) % (2 * np.pi) - np.pi  # box length runs along box y
        size = np.broadcast_to(np.array([self.width, self.length]), (len(self.s), 2))
        return np.concatenate([centres, size, yaw[:, None]], 1)


def _pick(rng: np.random.Generator, mix: dict[str, float]) -> str:
    names = list(mix)
    return str(rng.choice(names, p=np.array([mix[n] for n in names]) / sum(mix.values())))


def _size(rng: np.random.Generator, class_name: str) -> tuple[float, float, float]:
    (w0, w1), (l0, l1), brightness = CLASS_SHAPES[class_name]
    return float(rng.uniform(w0, w1)), float(rng.uniform(l0, l1)), brightness * float(rng.uniform(0.7, 1.4))


def _clear(s: np.ndarray, length: float, others: list[tuple[np.ndarray, float]]) -> bool:
    """True when a vehicle at arc lengths s [T] keeps a 2 m gap from every other one in its lane."""
    return all(np.all(np.abs(s - other) > (length + other_length) / 2.0 + 2.0) for other, other_length in others)


def spawn_traffic(
    rng: np.random.Generator, road: Road, times: np.ndarray, ego_s: np.ndarray, ego_offset: float, view: float, density: float
) -> list[Agent]:
    """Moving vehicles in every lane, parked vehicles at the kerbs, cyclists and pedestrians, placed so
    that they enter and leave the sensor's `view` (metres) while the ego drives `ego_s`."""
    duration = times[-1] - times[0]
    rel_t = times - times[0]
    lo, hi = ego_s.min() - view - 20.0, ego_s.max() + view + 20.0
    agents: list[Agent] = []
    lanes: dict[float, list[tuple[np.ndarray, float]]] = {}
    half = road.half_width

    def add(class_name: str, s: np.ndarray, offset: float | np.ndarray, direction: int, lane_key: float | None) -> None:
        width, length, brightness = _size(rng, class_name)
        if lane_key is not None:
            occupied = lanes.setdefault(lane_key, [])
            if not _clear(s, length, occupied):
                return
            occupied.append((s, length))
        offsets = np.broadcast_to(np.asarray(offset, dtype=np.float64), s.shape).copy()
        agents.append(Agent(len(agents) + 1, class_name, width, length, brightness, s, offsets, direction))

    lane_centres = [LANE_WIDTH * (k + 0.5) for k in range(road.lanes_per_direction)]
    lanes[ego_offset] = [(ego_s, EGO_LENGTH)]
    for centre in lane_centres:
        # Same direction: own speed profiles; the lane-gap check rejects collisions with the ego.
        for _ in range(rng.poisson(density * (hi - lo) / 45.0)):
            s0 = rng.uniform(lo, hi)
            s = s0 + speed_profile(rng, rel_t, max_speed=rng.uniform(7.0, 15.0), stop_probability=0.05)
            add(_pick(rng, TRAFFIC_MIX), s, centre, +1, centre)
        # Oncoming: start further out so that they drive into view during the sequence.
        for _ in range(rng.poisson(density * (hi - lo + 15.0 * duration) / 40.0)):
            s0 = rng.uniform(lo, hi + 15.0 * duration)
            s = s0 - speed_profile(rng, rel_t, max_speed=rng.uniform(6.0, 15.0), stop_probability=0.03)
            add(_pick(rng, TRAFFIC_MIX), s, -centre, -1, -centre)
    # Cyclists keep to the left edge of the ego's carriageway.
    for _ in range(rng.poisson(density * (hi - lo) / 250.0)):
        s = rng.uniform(lo, hi) + speed_profile(rng, rel_t, max_speed=rng.uniform(3.0, 7.0), stop_probability=0.0)
        add("bicycle", s, half - 0.45, +1, half - 0.45)
    # Parked vehicles in a parking strip outside the carriageway, on one or both sides.
    for side in (1.0, -1.0):
        if rng.random() < 0.6:
            continue
        position = lo + rng.uniform(0.0, 10.0)
        while position < hi:
            if rng.random() < 0.6:
                s = np.full_like(rel_t, position)
                add(_pick(rng, PARKED_MIX), s, side * (half + 1.1), int(side), side * (half + 1.1))
            position += rng.uniform(5.5, 14.0)
    # A few pedestrians on the pavements (dropped by the benchmark protocol, still annotated).
    for _ in range(rng.poisson(density * (hi - lo) / 120.0)):
        side = float(rng.choice([-1.0, 1.0]))
        kind = "pedestrian" if rng.random() < 0.75 else "group_of_pedestrians"
        walk = rng.uniform(0.8, 1.6) * rng.choice([-1.0, 1.0])
        s = rng.uniform(lo, hi) + walk * rel_t
        add(kind, s, side * (half + 3.3), 1 if walk > 0 else -1, None)
    return agents
