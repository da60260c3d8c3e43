"""How a road user looks to the Navtech, and the box RADIATE's annotators draw around it.

Real vehicles within 30 m are faint, smooth, partly filled blobs (mean grey ~32 inside their box, peak ~84, ~18 in a
2 m ring, never saturated) rather than crisp outlines. A road user's return here is a diffuse cloud: points spread
uniformly over the VISIBLE part of its body (a sub-rectangle on the side facing the radar: partly filled) and
blurred beyond it by `spread` metres (mirrors, wheels, multipath), summed in power (rafd.sim.sensor accumulates
diffuse scatterers additively), with a few glints. Its strength is drawn per road user over a wide range, so some
are barely above the noise floor, as in fog.

Annotators draw the box around the whole blurred return (rafd.sim.sequence applies their 180-degree and
width/length ambiguity afterwards): the body widened by the blur the sensor adds across and along its axes at its
range and bearing (beam width across range, range spread along it) plus a loose margin, so a car's label is about
2.6-3.0 m x 5 m where its body is 1.85 x 4.5 m.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from rafd.sim.scene import Scatterers

POINTS_PER_M2 = 40.0
# Per-class strength relative to a car (radar cross-section grows with size; two-wheelers and people are weak).
CLASS_STRENGTH = {
    "car": 1.0,
    "van": 1.3,
    "truck": 1.8,
    "bus": 1.8,
    "motorbike": 0.45,
    "bicycle": 0.3,
    "pedestrian": 0.2,
    "group_of_pedestrians": 0.3,
}
STRENGTH_RANGE = (0.4, 14.0)  # mean power per polar cell over the visible body, noise floor = 1 (log-uniform)
SPREAD_RANGE = (0.25, 0.7)  # metres
LABEL_SLACK = (0.05, 0.35)  # metres an annotator leaves on every side
LARGE_CLASS_EXTRA = 0.6  # metres: buses and trucks smear much wider across (height, multipath)


@dataclass(frozen=True)
class Look:
    strength: float  # mean power per polar cell over the visible body (noise floor = 1), before range loss
    visible: tuple[float, float, float, float]  # visible part: (u0, u1, v0, v1) in [-0.5, 0.5] of width, length
    spread: float  # metres
    glints: int  # strong point returns (wheel arches, mirrors, number plates)


def sample_look(rng: np.random.Generator, class_name: str, gain: float = 1.0) -> Look:
    """A road user's appearance; `gain` scales the strength (weather, sensor gain of the sequence)."""
    lo, hi = STRENGTH_RANGE
    strength = math.exp(rng.uniform(math.log(lo), math.log(hi))) * CLASS_STRENGTH.get(class_name, 1.0) * gain
    width_part, length_part = rng.uniform(0.5, 1.0), rng.uniform(0.4, 1.0)
    # placed on the body later (it depends on where the radar is); stored as sizes and a random along-shift
    shift = rng.uniform(-0.5, 0.5) * (1.0 - length_part)
    return Look(
        strength, (width_part, 0.0, length_part, shift), float(rng.uniform(*SPREAD_RANGE)), int(rng.poisson(1.5))
    )


def _visible_part(box: np.ndarray, look: Look) -> tuple[float, float, float, float]:
    """(u0, u1, v0, v1) metres in the body frame of the part facing the radar (the sensor at the ego origin)."""
    x, y, width, length, yaw = box
    c, s = math.cos(yaw), math.sin(yaw)
    towards = np.array([c * -x + s * -y, -s * -x + c * -y])  # direction to the radar in body axes
    width_part, _, length_part, shift = look.visible
    w, ln = width * width_part, length * length_part
    u_centre = math.copysign((width - w) / 2.0, towards[0])  # the side the radar sees
    v_room = (length - ln) / 2.0
    v_centre = float(np.clip(math.copysign(v_room, towards[1]) * 0.5 + shift * length, -v_room, v_room))
    return u_centre - w / 2.0, u_centre + w / 2.0, v_centre - ln / 2.0, v_centre + ln / 2.0


def diffuse_returns(
    box: np.ndarray, look: Look, rng: np.random.Generator, owner: int, azimuth_bin_rad: float, range_bin: float
) -> Scatterers:
    """A road user's return as diffuse scatterers in the ego frame (its box [5] in the ego frame).

    Point powers are normalised by the polar cell area at the road user's range, so `look.strength` is the mean power
    per cell whatever the range (the sensor's own range loss applies on top)."""
    u0, u1, v0, v1 = _visible_part(box, look)
    area = max((u1 - u0) * (v1 - v0), 0.05)
    count = max(int(POINTS_PER_M2 * (area + 4.0 * look.spread * (u1 - u0 + v1 - v0))), 8)
    local = np.stack([rng.uniform(u0, u1, count), rng.uniform(v0, v1, count)], -1)
    local += rng.normal(0.0, look.spread, local.shape)
    x, y, _, _, yaw = box
    c, s = math.cos(yaw), math.sin(yaw)
    xy = local @ np.array([[c, s], [-s, c]]) + np.array([x, y])
    distance = max(math.hypot(x, y), 1.0)
    cell_area = range_bin * distance * azimuth_bin_rad  # m^2 of one polar cell there
    density = count / (area + 2.0 * look.spread * (u1 - u0 + v1 - v0))  # points per m^2 over the blurred body
    power = look.strength / max(density * cell_area, 1e-3)  # summed per cell: mean cell power = strength
    amplitude = np.full(count, power) * rng.lognormal(0.0, 0.35, count)
    if look.glints:
        pick = rng.integers(0, count, look.glints)
        amplitude[pick] *= rng.uniform(3.0, 10.0, look.glints)
    n = len(xy)
    return Scatterers(xy, amplitude, np.zeros((n, 2)), np.ones(n, bool), np.full(n, owner), np.ones(n, bool))


def annotation_box(
    box: np.ndarray, class_name: str, look: Look, rng: np.random.Generator, beam_sigma_rad: float, range_sigma_m: float
) -> np.ndarray:
    """The box [5] an annotator draws around the road user's blurred return (ego frame, before the ambiguity)."""
    x, y, width, length, yaw = box
    distance = math.hypot(x, y)
    bearing = math.atan2(y, x)  # direction from the radar, counter-clockwise from ego x
    across = math.hypot(look.spread, distance * beam_sigma_rad)  # blur across the line of sight
    along = math.hypot(look.spread, range_sigma_m)  # blur along it
    # the body's width axis (box x) makes angle phi with the line of sight
    phi = yaw - bearing
    margin_w = math.hypot(along * math.cos(phi), across * math.sin(phi))
    margin_l = math.hypot(along * math.sin(phi), across * math.cos(phi))
    extra = LARGE_CLASS_EXTRA if class_name in ("bus", "truck") else 0.0
    new_width = width + 2.0 * (margin_w + rng.uniform(*LABEL_SLACK)) + extra
    new_length = length + 2.0 * (margin_l + rng.uniform(*LABEL_SLACK))
    return np.array([x, y, new_width, new_length, yaw])
