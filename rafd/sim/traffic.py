"""Road users of RADIATE's classes on the town's streets: traffic both ways on the ego's route and on the other
streets, parked vehicles (from the town's layout) and pedestrians on the pavements.

Every agent carries its world boxes on the simulation's fine time grid (several samples per scan), so a scan can
see each road user at the moment its beam passes it (rafd.sim.sequence).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rafd.sim.city import LANE_WIDTH, City, Street
from rafd.sim.road import ROAD_STEP, Road, speed_profile

# class -> ((width range), (length range)) of the body, metres
CLASS_SHAPES: dict[str, tuple[tuple[float, float], tuple[float, float]]] = {
    "car": ((1.7, 1.95), (4.0, 4.9)),
    "van": ((1.9, 2.2), (4.8, 6.0)),
    "truck": ((2.4, 2.6), (7.5, 12.0)),
    "bus": ((2.5, 2.6), (10.5, 12.5)),
    "motorbike": ((0.7, 0.9), (1.8, 2.3)),
    "bicycle": ((0.5, 0.7), (1.6, 1.9)),
    "pedestrian": ((0.5, 0.7), (0.5, 0.7)),
    "group_of_pedestrians": ((1.5, 3.0), (1.5, 3.0)),
}
TRAFFIC_MIX = {"car": 0.66, "van": 0.14, "truck": 0.06, "bus": 0.05, "motorbike": 0.05, "bicycle": 0.04}
EGO_LENGTH = 4.7


@dataclass(frozen=True)
class Agent:
    id: int
    class_name: str
    boxes: np.ndarray  # [F, 5] world (x, y, width, length, yaw) on the fine time grid; length along travel
    moving: bool


def street_road(street: Street, lo: float, hi: float) -> Road:
    """A straight Road along a town street from coordinate lo to hi (offsets to its left, like the city's)."""
    s = np.arange(lo, hi + ROAD_STEP, ROAD_STEP)
    if street.axis == 1:  # along +y at constant x
        points, heading = np.stack([np.full_like(s, street.position), s], -1), np.full_like(s, np.pi / 2)
    else:  # along +x at constant y
        points, heading = np.stack([s, np.full_like(s, street.position)], -1), np.zeros_like(s)
    return Road(s=s, points=points, heading=heading, lanes_per_direction=street.lanes)


def _size(rng: np.random.Generator, class_name: str) -> tuple[float, float]:
    (w0, w1), (l0, l1) = CLASS_SHAPES[class_name]
    return float(rng.uniform(w0, w1)), float(rng.uniform(l0, l1))


def _pick(rng: np.random.Generator, mix: dict[str, float]) -> str:
    names = list(mix)
    return str(rng.choice(names, p=np.array([mix[n] for n in names]) / sum(mix.values())))


def _boxes_on(road: Road, s: np.ndarray, offset: float, width: float, length: float, direction: int) -> np.ndarray:
    """[F] arc lengths on a road -> [F, 5] world boxes, length along the direction of travel."""
    centres, heading = road.frame_at(s, offset)
    travel = heading + (0.0 if direction > 0 else np.pi)
    yaw = (travel - np.pi / 2.0 + np.pi) % (2 * np.pi) - np.pi  # box length runs along box y
    return np.concatenate([centres, np.broadcast_to([width, length], (len(s), 2)), yaw[:, None]], 1)


def _clear(s: np.ndarray, length: float, others: list[tuple[np.ndarray, float]]) -> bool:
    """True when a vehicle at arc lengths s keeps a 2 m gap from every other one in its lane."""
    return all(np.all(np.abs(s - other) > (length + other_length) / 2.0 + 2.0) for other, other_length in others)


def spawn_traffic(
    rng: np.random.Generator,
    city: City,
    route: Road,
    times: np.ndarray,
    ego_s: np.ndarray,
    ego_offset: float,
    view: float,
    density: float,
) -> list[Agent]:
    """Road users for a drive whose ego follows `route` at arc lengths ego_s [F] on the fine time grid `times` [F].

    density scales moving traffic: vehicles per lane per 45 m (0 = empty streets)."""
    rel_t = times - times[0]
    duration = rel_t[-1]
    agents: list[Agent] = []

    def add(class_name: str, boxes: np.ndarray, moving: bool) -> None:
        agents.append(Agent(len(agents) + 1, class_name, boxes, moving))

    def lane_traffic(road: Road, lo: float, hi: float, occupied: dict[float, list[tuple[np.ndarray, float]]]) -> None:
        for k in range(road.lanes_per_direction):
            for direction in (1, -1):
                offset = direction * LANE_WIDTH * (k + 0.5)
                lane = occupied.setdefault(offset, [])
                span = hi - lo + 15.0 * duration
                for _ in range(rng.poisson(density * span / 45.0)):
                    class_name = _pick(rng, TRAFFIC_MIX)
                    width, length = _size(rng, class_name)
                    travelled = speed_profile(rng, rel_t, max_speed=rng.uniform(5.0, 14.0), stop_probability=0.05)
                    start = rng.uniform(
                        lo - (15.0 * duration if direction > 0 else 0.0),
                        hi + (15.0 * duration if direction < 0 else 0.0),
                    )
                    s = start + direction * travelled
                    if not _clear(s, length, lane):
                        continue
                    lane.append((s, length))
                    add(class_name, _boxes_on(road, s, offset, width, length, direction), True)

    lo, hi = ego_s.min() - view - 20.0, ego_s.max() + view + 20.0
    lane_traffic(route, lo, hi, {ego_offset: [(ego_s, EGO_LENGTH)]})
    ego_xy, _ = route.frame_at(ego_s, ego_offset)
    x_lo, y_lo = ego_xy.min(axis=0) - view - 20.0
    x_hi, y_hi = ego_xy.max(axis=0) + view + 20.0
    ego_street = route.points[0, 0]
    for street in city.x_streets + city.y_streets:
        if street.axis == 1 and abs(street.position - ego_street) < 1e-6:
            continue  # the route's own street (its traffic is above)
        coordinate = street.position
        if not ((x_lo < coordinate < x_hi) if street.axis == 1 else (y_lo < coordinate < y_hi)):
            continue  # out of the sensor's reach during the drive
        a, b = (y_lo, y_hi) if street.axis == 1 else (x_lo, x_hi)
        lane_traffic(street_road(street, a - 60.0, b + 60.0), a, b, {})
    for box in city.parked:
        if x_lo < box[0] < x_hi and y_lo < box[1] < y_hi:
            add("van" if box[3] > 5.0 else "car", np.broadcast_to(box, (len(times), 5)).copy(), False)
    # pedestrians on the pavements of the route (dropped by the benchmark protocol, still annotated)
    for _ in range(rng.poisson(max(density, 0.2) * (hi - lo) / 80.0)):
        side = float(rng.choice([-1.0, 1.0]))
        kind = "pedestrian" if rng.random() < 0.8 else "group_of_pedestrians"
        width, length = _size(rng, kind)
        walk = rng.uniform(0.8, 1.6) * rng.choice([-1.0, 1.0])
        s = rng.uniform(lo, hi) + walk * rel_t
        offset = side * (route.half_width + 1.5)
        add(kind, _boxes_on(route, s, offset, width, length, 1 if walk > 0 else -1), True)
    return agents
