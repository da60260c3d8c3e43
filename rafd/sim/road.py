"""A winding road centreline in a world frame and the ego vehicle's drive along it."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ROAD_STEP = 0.5  # metres between centreline samples
LANE_WIDTH = 3.5  # metres (UK urban lane)


@dataclass(frozen=True)
class Road:
    """Centreline sampled every ROAD_STEP metres of arc length s; lateral offsets are positive to the
    left of the direction of increasing s (UK traffic keeps left, so the ego's lanes have offset > 0)."""

    s: np.ndarray  # [K] arc length, increasing
    points: np.ndarray  # [K, 2] world metres
    heading: np.ndarray  # [K] radians, CCW from world x, direction of increasing s
    lanes_per_direction: int

    @property
    def half_width(self) -> float:
        return self.lanes_per_direction * LANE_WIDTH

    def frame_at(self, s: np.ndarray, offset: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """[...] arc lengths and lateral offsets -> ([..., 2] world points, [...] road headings)."""
        s = np.asarray(s, dtype=np.float64)
        cos_h = np.interp(s, self.s, np.cos(self.heading))
        sin_h = np.interp(s, self.s, np.sin(self.heading))
        heading = np.arctan2(sin_h, cos_h)
        x = np.interp(s, self.s, self.points[:, 0]) - np.sin(heading) * offset
        y = np.interp(s, self.s, self.points[:, 1]) + np.cos(heading) * offset
        return np.stack([x, y], -1), heading


def make_road(rng: np.random.Generator, s_min: float, s_max: float, start_offset: float) -> Road:
    """Piecewise-constant curvature (straights and bends, smoothed into clothoid-like transitions),
    placed so that the point at s = 0, lateral `start_offset`, is the world origin heading along +y."""
    s = np.arange(s_min, s_max + ROAD_STEP, ROAD_STEP)
    curvature = np.zeros_like(s)
    position = s_min
    while position < s_max:
        length = rng.uniform(40.0, 140.0)
        if rng.random() < 0.45:
            value = 0.0
        else:
            value = rng.choice([-1.0, 1.0]) * rng.uniform(1.0 / 250.0, 1.0 / 40.0)
        curvature[(s >= position) & (s < position + length)] = value
        position += length
    window = int(25.0 / ROAD_STEP)  # 25 m transition between curvatures
    curvature = np.convolve(np.pad(curvature, window // 2, mode="edge"), np.ones(window) / window, "valid")[: len(s)]
    heading = np.cumsum(curvature) * ROAD_STEP
    heading = heading - np.interp(0.0, s, heading) + np.pi / 2.0  # heading +y (ego forward) at s = 0
    steps = np.stack([np.cos(heading), np.sin(heading)], -1) * ROAD_STEP  # [K, 2]
    points = np.cumsum(steps, 0)
    points -= np.array([np.interp(0.0, s, points[:, 0]), np.interp(0.0, s, points[:, 1])])
    road = Road(s=s, points=points, heading=heading, lanes_per_direction=int(rng.choice([1, 2], p=[0.65, 0.35])))
    # Shift so the ego's start (s = 0 at its lane offset) is the world origin.
    start, _ = road.frame_at(np.array(0.0), start_offset)
    return Road(s=s, points=points - start, heading=heading, lanes_per_direction=road.lanes_per_direction)


def speed_profile(
    rng: np.random.Generator, times: np.ndarray, max_speed: float, stop_probability: float, initial: float | None = None
) -> np.ndarray:
    """[T] increasing times -> [T] arc lengths travelled from 0, following random target speeds
    (held 2-6 s, occasionally 0 = a stop) with bounded acceleration."""
    fine_dt = 0.05
    fine_t = np.arange(0.0, times[-1] + fine_dt, fine_dt)
    speed = rng.uniform(0.3, 1.0) * max_speed if initial is None else initial
    target, hold_until = speed, 0.0
    distance = np.zeros_like(fine_t)
    for i in range(1, len(fine_t)):
        if fine_t[i] >= hold_until:
            target = 0.0 if rng.random() < stop_probability else rng.uniform(0.25, 1.0) * max_speed
            hold_until = fine_t[i] + rng.uniform(2.0, 6.0)
        limit = (2.5 if target > speed else 3.5) * fine_dt  # m/s per step: gentle accel, firmer braking
        speed += float(np.clip(target - speed, -limit, limit))
        distance[i] = distance[i - 1] + speed * fine_dt
    return np.interp(times, fine_t, distance)


@dataclass(frozen=True)
class EgoDrive:
    s: np.ndarray  # [T] arc length per frame
    offset: np.ndarray  # [T] lateral offset per frame
    poses: np.ndarray  # [T, 3] world (x, y, yaw) of the radar's ego frame (ego y = forward)


def drive_ego(rng: np.random.Generator, road: Road, times: np.ndarray, lane_offset: float) -> EgoDrive:
    """The ego follows its lane with a varying speed and a slight lateral weave; yaw follows the road."""
    s = speed_profile(rng, times - times[0], max_speed=rng.uniform(8.0, 14.0), stop_probability=0.12)
    weave = 0.25 * np.sin(2 * np.pi * (times - times[0]) / rng.uniform(4.0, 9.0) + rng.uniform(0, 2 * np.pi))
    offset = lane_offset + weave
    points, heading = road.frame_at(s, offset)
    # Heading correction from the weave: d(offset)/ds, guarded where the ego stands still.
    # np.gradient needs two samples: a one-frame drive has no weave slope.
    ds = np.gradient(s) if len(s) > 1 else np.zeros_like(s)
    d_offset = np.gradient(offset) if len(s) > 1 else np.zeros_like(s)
    slope = np.where(ds > 0.05, d_offset / np.maximum(ds, 0.05), 0.0)
    yaw = heading + np.arctan(np.clip(slope, -0.1, 0.1)) - np.pi / 2.0  # ego +y along travel
    yaw = (yaw + np.pi) % (2 * np.pi) - np.pi
    return EgoDrive(s=s, offset=offset, poses=np.concatenate([points, yaw[:, None]], 1))
