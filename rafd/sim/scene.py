"""Radar scatterers of the world: static structure along the road and the road users' bodies."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rafd.sim.road import Road
from rafd.sim.traffic import Agent

PARKING_STRIP = 2.2  # metres between the carriageway edge and the kerb (parked cars stand in it)


@dataclass(frozen=True)
class Scatterers:
    """Point reflectors; `normal` is zero for isotropic ones; `owner` is -1 for static world."""

    xy: np.ndarray  # [N, 2] metres
    amplitude: np.ndarray  # [N] power relative to the noise floor
    normal: np.ndarray  # [N, 2] unit outward normal, or 0
    occluder: np.ndarray  # [N] bool: casts a radar shadow behind it
    owner: np.ndarray  # [N] int

    @staticmethod
    def concat(parts: list["Scatterers"]) -> "Scatterers":
        return Scatterers(
            xy=np.concatenate([p.xy for p in parts]),
            amplitude=np.concatenate([p.amplitude for p in parts]),
            normal=np.concatenate([p.normal for p in parts]),
            occluder=np.concatenate([p.occluder for p in parts]),
            owner=np.concatenate([p.owner for p in parts]),
        )

    def transformed(self, rotation: np.ndarray, translation: np.ndarray) -> "Scatterers":
        """Apply p -> rotation @ p + translation (rotation [2, 2]) to points and normals."""
        return Scatterers(self.xy @ rotation.T + translation, self.amplitude, self.normal @ rotation.T, self.occluder, self.owner)


def _along(road: Road, s: np.ndarray, offset: np.ndarray, amplitude: np.ndarray, facing: float, occluder: bool) -> Scatterers:
    """Scatterers at road coordinates; `facing` +1/-1 makes normals point to the left/right of the road, 0 = isotropic."""
    xy, heading = road.frame_at(s, offset)
    left = np.stack([-np.sin(heading), np.cos(heading)], -1)
    return Scatterers(xy, amplitude, left * facing, np.full(len(s), occluder), np.full(len(s), -1))


def _cross(road: Road, s: float, offsets: np.ndarray, amplitude: np.ndarray, facing: float) -> Scatterers:
    """A wall perpendicular to the road at arc length s; normals along +-road direction (`facing`)."""
    xy, heading = road.frame_at(np.full(len(offsets), s), offsets)
    forward = np.stack([np.cos(heading), np.sin(heading)], -1)
    return Scatterers(xy, amplitude, forward * facing, np.ones(len(offsets), bool), np.full(len(offsets), -1))


def build_static_world(rng: np.random.Generator, road: Road, s_lo: float, s_hi: float, clutter: float) -> Scatterers:
    """Kerbs, building facades (with side walls), fences, hedges, poles and diffuse vegetation/ground
    patches on both sides of the road between arc lengths s_lo and s_hi."""
    parts: list[Scatterers] = []
    kerb = road.half_width + PARKING_STRIP
    for side in (1.0, -1.0):
        inward = -side  # normals of roadside structure face the road
        s = np.arange(s_lo, s_hi, 0.3)
        keep = rng.random(len(s)) < 0.7
        parts.append(_along(road, s[keep], side * kerb, rng.lognormal(np.log(6.0), 0.7, keep.sum()), inward, False))
        position = s_lo
        while position < s_hi:
            length = rng.uniform(8.0, 55.0)
            kind = rng.choice(["facade", "fence", "hedge", "open"], p=[0.5, 0.15, 0.15, 0.2])
            setback = side * (kerb + rng.uniform(2.0, 4.0) + (rng.uniform(0.0, 10.0) if rng.random() < 0.4 else 0.0))
            seg = np.arange(position, min(position + length, s_hi), 0.2)
            if kind == "facade" and len(seg) > 1:
                base = rng.uniform(25.0, 100.0)
                texture = base * rng.lognormal(0.0, 0.8, len(seg))
                texture *= 1.0 + 3.0 * (rng.random(len(seg)) < 0.03)  # doors, drainpipes, window frames
                parts.append(_along(road, seg, np.full(len(seg), setback), texture, inward, True))
                depth = side * np.arange(0.0, rng.uniform(6.0, 25.0), 0.2)
                for end, facing in ((seg[0], -1.0), (seg[-1], 1.0)):
                    offsets = setback + depth
                    parts.append(_cross(road, float(end), offsets, base * rng.lognormal(0.0, 0.8, len(offsets)), facing))
            elif kind == "fence" and len(seg) > 1:
                posts = np.arange(seg[0], seg[-1], rng.uniform(1.5, 3.0))
                parts.append(_along(road, posts, np.full(len(posts), setback), rng.uniform(20.0, 60.0, len(posts)), 0.0, False))
                parts.append(_along(road, seg, np.full(len(seg), setback), rng.lognormal(np.log(5.0), 0.5, len(seg)), inward, False))
            elif kind == "hedge" and len(seg) > 1:
                count = int(len(seg) * 4)
                s_pts = rng.uniform(seg[0], seg[-1], count)
                off = setback + side * rng.uniform(0.0, rng.uniform(1.0, 3.0), count)
                parts.append(_along(road, s_pts, off, rng.lognormal(np.log(10.0), 0.8, count), 0.0, True))
            position += length + (rng.uniform(1.0, 6.0) if rng.random() < 0.7 else rng.uniform(10.0, 30.0))
        # Poles, sign posts, trees at the kerb.
        poles = np.cumsum(rng.uniform(10.0, 35.0, int((s_hi - s_lo) / 10.0) + 1)) + s_lo
        poles = poles[poles < s_hi]
        parts.append(_along(road, poles, np.full(len(poles), side * (kerb + 0.6)), rng.uniform(60.0, 250.0, len(poles)), 0.0, True))
        # Diffuse patches beyond the roadside: vegetation, car parks, rough ground (radar "texture").
        for _ in range(rng.poisson(clutter * (s_hi - s_lo) / 5.0)):
            centre_s = rng.uniform(s_lo, s_hi)
            centre_off = side * (kerb + rng.uniform(4.0, 90.0))
            radius = rng.uniform(2.5, 14.0)
            count = int(rng.uniform(8.0, 16.0) * radius * radius)
            r = radius * np.sqrt(rng.random(count))
            a = rng.uniform(0, 2 * np.pi, count)
            amp = rng.uniform(2.0, 8.0) * rng.lognormal(0.0, 0.4, count)
            parts.append(_along(road, centre_s + r * np.cos(a), centre_off + r * np.sin(a), amp, 0.0, False))
    parts.extend(_buildings(rng, road, s_lo, s_hi, kerb, clutter))
    return Scatterers.concat(parts)


def _buildings(rng: np.random.Generator, road: Road, s_lo: float, s_hi: float, kerb: float, clutter: float) -> list[Scatterers]:
    """Detached buildings and car-park walls away from the road: rectangles of outward-facing walls."""
    parts = []
    for _ in range(rng.poisson(clutter * (s_hi - s_lo) / 15.0)):
        centre, heading = road.frame_at(np.array(rng.uniform(s_lo, s_hi)), rng.choice([-1.0, 1.0]) * (kerb + rng.uniform(15.0, 90.0)))
        w, l = rng.uniform(6.0, 30.0, 2)
        yaw = float(heading) + rng.normal(0.0, 0.15)
        base = rng.uniform(15.0, 70.0)
        for (x0, y0), (x1, y1), normal in (
            ((-w / 2, l / 2), (w / 2, l / 2), (0.0, 1.0)),
            ((w / 2, l / 2), (w / 2, -l / 2), (1.0, 0.0)),
            ((w / 2, -l / 2), (-w / 2, -l / 2), (0.0, -1.0)),
            ((-w / 2, -l / 2), (-w / 2, l / 2), (-1.0, 0.0)),
        ):
            t = np.arange(0.0, 1.0, 0.2 / max(np.hypot(x1 - x0, y1 - y0), 0.2))
            local = np.stack([x0 + (x1 - x0) * t, y0 + (y1 - y0) * t], -1)
            rotation = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
            n = len(t)
            parts.append(
                Scatterers(local @ rotation.T + centre, base * rng.lognormal(0.0, 0.8, n), np.tile(rotation @ np.array(normal), (n, 1)), np.ones(n, bool), np.full(n, -1))
            )
    return parts


@dataclass(frozen=True)
class BodyModel:
    """Scatterers on a vehicle's outline in its own box frame (x across, y along), fixed glints."""

    local: Scatterers


def body_model(rng: np.random.Generator, agent: Agent, index: int) -> BodyModel:
    """Outline points every 0.15 m with outward normals; a few strong glints (wheel arches, mirrors,
    corners) and weak underbody points, scaled by the class brightness."""
    w, l = agent.width, agent.length
    points, normals = [], []
    for (x0, y0), (x1, y1), normal in (
        ((-w / 2, l / 2), (w / 2, l / 2), (0.0, 1.0)),
        ((w / 2, l / 2), (w / 2, -l / 2), (1.0, 0.0)),
        ((w / 2, -l / 2), (-w / 2, -l / 2), (0.0, -1.0)),
        ((-w / 2, -l / 2), (-w / 2, l / 2), (-1.0, 0.0)),
    ):
        count = max(int(np.hypot(x1 - x0, y1 - y0) / 0.15), 2)
        t = (np.arange(count) + 0.5) / count
        points.append(np.stack([x0 + (x1 - x0) * t, y0 + (y1 - y0) * t], -1))
        normals.append(np.tile(normal, (count, 1)))
    xy, normal = np.concatenate(points), np.concatenate(normals)
    amplitude = 90.0 * agent.brightness * rng.lognormal(0.0, 0.7, len(xy))
    glints = rng.random(len(xy)) < 0.08
    amplitude[glints] *= rng.uniform(3.0, 8.0, glints.sum())
    inner = rng.uniform(-0.45, 0.45, (max(int(3 * w * l), 2), 2)) * np.array([w, l])
    xy = np.concatenate([xy, inner])
    normal = np.concatenate([normal, np.zeros_like(inner)])
    amplitude = np.concatenate([amplitude, 40.0 * agent.brightness * rng.lognormal(0.0, 0.5, len(inner))])
    n = len(xy)
    return BodyModel(Scatterers(xy, amplitude, normal, np.ones(n, bool), np.full(n, index)))
