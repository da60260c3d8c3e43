"""The ego's route through the town (a street, possibly turning at a junction) and its drive along it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rafd.sim.city import LANE_WIDTH

ROAD_STEP = 0.5  # metres between centreline samples


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


def make_route(
    street_x: float,
    s_min: float,
    s_max: float,
    lanes: int,
    turn: int = 0,
    junction_y: float = 0.0,
    radius: float = 10.0,
) -> Road:
    """The centreline of the ego's street (world x = street_x, heading +y, arc length s = world y before any turn);
    turn +1 (left) / -1 (right) leaves it on a quarter circle of `radius` into the crossing street at world
    y = junction_y, whose centreline the route then follows; 0 keeps straight on."""
    s = np.arange(s_min, s_max + ROAD_STEP, ROAD_STEP)
    heading = np.full_like(s, np.pi / 2.0)
    points = np.stack([np.full_like(s, street_x), s], -1)  # straight on along +y
    if turn:
        start, length = junction_y - radius, radius * np.pi / 2.0  # the arc ends on the crossing street's centreline
        angle = np.clip(s - start, 0.0, length) / radius  # turned so far, [0, pi/2]
        centre = np.array([street_x - turn * radius, start])
        on_arc = s > start
        points[on_arc, 0] = centre[0] + turn * radius * np.cos(angle[on_arc])
        points[on_arc, 1] = centre[1] + radius * np.sin(angle[on_arc])
        heading[on_arc] = np.pi / 2.0 + turn * angle[on_arc]
        beyond = s > start + length  # then straight on along the crossing street
        points[beyond] += (s[beyond] - start - length)[:, None] * np.stack(
            [np.cos(heading[beyond]), np.sin(heading[beyond])], -1
        )
    return Road(s=s, points=points, heading=heading, lanes_per_direction=lanes)


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
