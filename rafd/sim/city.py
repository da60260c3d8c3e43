"""A street-grid town in a world frame: streets, junctions, kerbs, building lines, poles, vegetation, car parks.

Streets run along world x and y (right-angled grid, blocks 35-160 m across, like the town centres RADIATE drives
through). Every street has a carriageway, continuous kerbs with gaps only at junctions and driveways, pavements,
and a building line behind them. Blocks are filled with buildings (textured facades with side walls), parks
(textured vegetation, trees), car parks (rows of parked cars) or open ground. Every static return is a point
scatterer (rafd.sim.scene.Scatterers); parked cars are returned separately as boxes (they are annotated objects).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rafd.sim.scene import Scatterers

LANE_WIDTH = 3.3  # metres (UK urban lane)
BLOCK_RANGE = (35.0, 160.0)  # block side, metres
KERB_STEP = 0.2  # metres between kerb / wall scatterers
STATIC_GAIN = 0.5  # every static return's power scales by this (matched to real scans by rafd-simulate --realism)


@dataclass(frozen=True)
class Street:
    axis: int  # 0: the street runs along world x (constant y), 1: along world y (constant x)
    position: float  # its centreline's constant coordinate, metres
    lanes: int  # lanes per direction
    pavement: float  # kerb to building line, metres

    @property
    def half_width(self) -> float:
        """Centreline to kerb, metres."""
        return self.lanes * LANE_WIDTH


@dataclass(frozen=True)
class City:
    x_streets: list[Street]  # streets running along y, at constant x (axis 1)
    y_streets: list[Street]  # streets running along x, at constant y (axis 0)
    bounds: tuple[float, float, float, float]  # x_lo, x_hi, y_lo, y_hi
    scatterers: Scatterers  # every static return, world frame
    parked: np.ndarray  # [N, 5] world boxes of parked vehicles (x, y, width, length, yaw)


def _street_lines(rng: np.random.Generator, lo: float, hi: float, first: float) -> list[float]:
    """Street positions covering [lo, hi], one of them at `first`."""
    positions = [first]
    while positions[-1] < hi:
        positions.append(positions[-1] + rng.uniform(*BLOCK_RANGE))
    while positions[0] > lo:
        positions.insert(0, positions[0] - rng.uniform(*BLOCK_RANGE))
    return positions


def _segment(start: np.ndarray, end: np.ndarray, step: float) -> np.ndarray:
    """[N, 2] points every `step` metres from start to end."""
    length = float(np.hypot(*(end - start)))
    count = max(int(length / step), 1)
    t = (np.arange(count) + 0.5) / count
    return start[None] + t[:, None] * (end - start)[None]


class _Builder:
    """Collects scatterers and parked cars while the town is laid out."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.parts: list[Scatterers] = []
        self.parked: list[np.ndarray] = []

    def add(self, xy: np.ndarray, amplitude: np.ndarray, normal: np.ndarray | None, occluder: bool) -> None:
        n = len(xy)
        if n == 0:
            return
        normal = np.zeros((n, 2)) if normal is None else np.broadcast_to(normal, (n, 2)).astype(np.float64)
        self.parts.append(
            Scatterers(
                np.asarray(xy, np.float64),
                np.asarray(amplitude, np.float64),
                normal,
                np.full(n, occluder),
                np.full(n, -1),
            )
        )

    def wall(
        self,
        start: np.ndarray,
        end: np.ndarray,
        normal: np.ndarray,
        base: float,
        occluder: bool = True,
        fill: float = 1.0,
        depth: float = 0.0,
    ) -> None:
        """A straight wall (facade, kerb, fence) of textured returns facing `normal`, spread over `depth` metres
        behind its line (recesses, balconies, windows: real building returns are thick bands)."""
        xy = _segment(start, end, KERB_STEP)
        if depth > 0:
            xy = xy - np.asarray(normal)[None] * self.rng.exponential(depth, (len(xy), 1))
        keep = self.rng.random(len(xy)) < fill
        texture = base * self.rng.lognormal(0.0, 0.7, len(xy))
        texture *= 1.0 + 3.0 * (self.rng.random(len(xy)) < 0.04)  # windows, doors, drainpipes
        # slow variation along the wall: materials, parked bikes, bins
        texture *= np.exp(
            0.5 * np.sin(np.arange(len(xy)) * KERB_STEP / self.rng.uniform(3, 15) + self.rng.uniform(0, 6))
        )
        self.add(xy[keep], texture[keep], normal, occluder)

    def blob(self, centre: np.ndarray, radius: float, base: float, occluder: bool) -> None:
        """Vegetation: a round patch whose returns have a multi-scale texture (leaves, branches, gaps)."""
        rng = self.rng
        count = int(rng.uniform(10.0, 18.0) * radius * radius)
        r = radius * np.sqrt(rng.random(count))
        a = rng.uniform(0, 2 * np.pi, count)
        xy = centre + np.stack([r * np.cos(a), r * np.sin(a)], -1)
        # texture: a few bright clumps over a weaker body, fading at the rim
        clumps = centre + rng.normal(0.0, radius * 0.5, (max(2, int(radius)), 2))
        near = np.min(np.hypot(*(xy[:, None] - clumps[None]).transpose(2, 0, 1)), axis=1)
        amplitude = base * rng.lognormal(0.0, 1.0, count) * (0.15 + 1.5 * np.exp(-near / max(radius * 0.25, 0.6)))
        amplitude *= 1.0 - 0.6 * (r / radius) ** 2
        self.add(xy, amplitude, None, occluder)

    def point(self, xy: np.ndarray, amplitude: float) -> None:
        """A pole, bollard or sign: a strong isotropic point return that shadows what is behind it."""
        self.add(np.asarray(xy, np.float64)[None], np.array([amplitude]), None, True)

    def parked_car(self, centre: np.ndarray, yaw: float) -> None:
        width, length = self.rng.uniform(1.7, 2.05), self.rng.uniform(3.9, 5.2)
        if self.rng.random() < 0.15:
            width, length = self.rng.uniform(1.95, 2.2), self.rng.uniform(5.0, 6.5)  # vans
        self.parked.append(np.array([centre[0], centre[1], width, length, yaw]))


def _along(street: Street, coordinate: np.ndarray | float, offset: float) -> np.ndarray:
    """World point(s) at `coordinate` along the street and `offset` to its left (+) / right (-) of the centreline."""
    coordinate = np.atleast_1d(np.asarray(coordinate, np.float64))
    if street.axis == 0:  # along x at constant y: left of +x is +y
        return np.stack([coordinate, np.full_like(coordinate, street.position + offset)], -1)
    return np.stack([np.full_like(coordinate, street.position - offset), coordinate], -1)  # left of +y is -x


def _left(street: Street) -> np.ndarray:
    return np.array([0.0, 1.0]) if street.axis == 0 else np.array([-1.0, 0.0])


def _gaps(crossings: list[tuple[float, float]], lo: float, hi: float) -> list[tuple[float, float]]:
    """Intervals of [lo, hi] outside the crossing streets' (centre, half width) spans."""
    pieces, position = [], lo
    for centre, half in sorted(crossings):
        if centre - half > position:
            pieces.append((position, min(centre - half, hi)))
        position = max(position, centre + half)
    if position < hi:
        pieces.append((position, hi))
    return [(a, b) for a, b in pieces if b - a > 0.5]


def build_city(
    rng: np.random.Generator,
    bounds: tuple[float, float, float, float],
    ego_street_x: Street,
    clutter: float = 1.0,
    parked_density: float = 1.0,
) -> City:
    """Lay out a street grid over `bounds` (x_lo, x_hi, y_lo, y_hi) containing `ego_street_x` (a street along y)."""
    x_lo, x_hi, y_lo, y_hi = bounds
    xs = _street_lines(rng, x_lo, x_hi, ego_street_x.position)
    ys = _street_lines(rng, y_lo, y_hi, rng.uniform(20.0, 90.0))

    def street(axis: int, position: float) -> Street:
        if axis == 1 and position == ego_street_x.position:
            return ego_street_x
        return Street(axis, position, int(rng.choice([1, 2], p=[0.7, 0.3])), rng.uniform(2.0, 4.5))

    x_streets = [street(1, x) for x in xs]
    y_streets = [street(0, y) for y in ys]
    build = _Builder(rng)
    for streets, crossing, (lo, hi) in ((x_streets, y_streets, (y_lo, y_hi)), (y_streets, x_streets, (x_lo, x_hi))):
        for s in streets:
            spans = [(c.position, c.half_width + c.pavement) for c in crossing]
            for side in (1.0, -1.0):
                inward = -side * _left(s)  # roadside structure faces the carriageway
                kerb, line = side * s.half_width, side * (s.half_width + s.pavement)
                for a, b in _gaps(spans, lo, hi):
                    position = a
                    while position < b:  # continuous kerb, broken by driveways
                        end = min(position + rng.uniform(15.0, 80.0), b)
                        build.wall(
                            _along(s, position, kerb)[0],
                            _along(s, end, kerb)[0],
                            inward,
                            rng.uniform(5.0, 16.0),
                            occluder=False,
                            fill=0.85,
                        )
                        position = end + (rng.uniform(3.0, 6.0) if rng.random() < 0.5 else 0.0)
                    for pole in np.arange(a + rng.uniform(0, 10), b, rng.uniform(12.0, 30.0)):  # poles, signs
                        build.point(_along(s, pole, kerb + side * rng.uniform(0.3, 0.8))[0], rng.uniform(60, 250))
                    # the building line: facades with setbacks, fences, hedges, or open frontage
                    position = a
                    while position < b:
                        end = min(position + rng.uniform(8.0, 45.0), b)
                        kind = rng.choice(["facade", "fence", "hedge", "open"], p=[0.55, 0.15, 0.15, 0.15])
                        setback = line + side * (rng.uniform(0.0, 6.0) if rng.random() < 0.4 else 0.0)
                        p, q = _along(s, position, setback)[0], _along(s, end, setback)[0]
                        if kind == "facade":
                            build.wall(p, q, inward, rng.uniform(30.0, 130.0), depth=rng.uniform(0.3, 1.5))
                            build.wall(p, q, inward, rng.uniform(10.0, 40.0), depth=rng.uniform(1.0, 3.0))
                            depth = side * _left(s) * rng.uniform(6.0, 20.0)
                            build.wall(p, p + depth, -(q - p) / max(np.hypot(*(q - p)), 1e-6), rng.uniform(12, 60))
                            build.wall(q, q + depth, (q - p) / max(np.hypot(*(q - p)), 1e-6), rng.uniform(12, 60))
                        elif kind == "fence":
                            build.wall(p, q, inward, rng.uniform(6.0, 20.0), occluder=False, fill=0.7)
                            for post in _segment(p, q, rng.uniform(1.5, 3.0)):
                                build.point(post, rng.uniform(15, 50))
                        elif kind == "hedge":
                            for centre in _segment(p, q, 1.6):
                                build.blob(
                                    centre + side * _left(s) * rng.uniform(0, 1.0),
                                    rng.uniform(0.8, 1.8),
                                    rng.uniform(8.0, 25.0) * clutter,
                                    occluder=True,
                                )
                        position = end + (rng.uniform(1.0, 8.0) if rng.random() < 0.5 else 0.0)
                    # trees on the pavement and occasional cars parked at the kerb (not every kerb)
                    for tree in np.arange(a + rng.uniform(0, 20), b, rng.uniform(6.0, 25.0)):
                        if rng.random() < 0.7:
                            build.blob(
                                _along(s, tree, kerb + side * s.pavement * 0.5)[0],
                                rng.uniform(1.5, 5.0),
                                rng.uniform(12.0, 45.0) * clutter,
                                occluder=True,
                            )
                    for garden in np.arange(a + rng.uniform(0, 15), b, rng.uniform(8.0, 30.0)):  # front gardens
                        if rng.random() < 0.5:
                            build.blob(
                                _along(s, garden, line + side * rng.uniform(2.0, 8.0))[0],
                                rng.uniform(2.0, 6.0),
                                rng.uniform(10.0, 40.0) * clutter,
                                occluder=True,
                            )
                    if rng.random() < 0.35 * parked_density:
                        yaw = 0.0 if s.axis == 1 else np.pi / 2  # box length along the street
                        position = a + rng.uniform(2.0, 20.0)
                        stop = min(b, position + rng.uniform(10.0, 60.0))
                        while position < stop:
                            build.parked_car(_along(s, position, kerb - side * 1.1)[0], yaw + rng.normal(0, 0.03))
                            position += rng.uniform(5.5, 12.0)
    # the blocks between the streets
    for xa, xb in zip(x_streets[:-1], x_streets[1:]):
        for ya, yb in zip(y_streets[:-1], y_streets[1:]):
            inner = (
                xa.position + xa.half_width + xa.pavement + 1.0,
                xb.position - xb.half_width - xb.pavement - 1.0,
                ya.position + ya.half_width + ya.pavement + 1.0,
                yb.position - yb.half_width - yb.pavement - 1.0,
            )
            if inner[1] - inner[0] < 8 or inner[3] - inner[2] < 8:
                continue
            _fill_block(build, inner, clutter, parked_density)
    scatterers = Scatterers.concat(build.parts)
    scatterers = Scatterers(
        scatterers.xy, scatterers.amplitude * STATIC_GAIN, scatterers.normal, scatterers.occluder, scatterers.owner
    )
    parked = np.stack(build.parked) if build.parked else np.zeros((0, 5))
    return City(x_streets, y_streets, bounds, scatterers, parked)


def _fill_block(
    build: _Builder, inner: tuple[float, float, float, float], clutter: float, parked_density: float
) -> None:
    """One block: buildings (walls facing out), a park (vegetation, trees), a car park, or open ground."""
    rng = build.rng
    x0, x1, y0, y1 = inner
    kind = rng.choice(["buildings", "park", "car_park", "open"], p=[0.55, 0.2, 0.15, 0.1])
    if kind == "buildings":
        for _ in range(rng.integers(1, 5)):
            w, h = rng.uniform(8.0, min(40.0, x1 - x0)), rng.uniform(8.0, min(40.0, y1 - y0))
            cx, cy = rng.uniform(x0 + w / 2, x1 - w / 2), rng.uniform(y0 + h / 2, y1 - h / 2)
            corners = np.array(
                [[cx - w / 2, cy - h / 2], [cx + w / 2, cy - h / 2], [cx + w / 2, cy + h / 2], [cx - w / 2, cy + h / 2]]
            )
            for k, normal in enumerate(([0.0, -1.0], [1.0, 0.0], [0.0, 1.0], [-1.0, 0.0])):
                build.wall(corners[k], corners[(k + 1) % 4], np.array(normal), rng.uniform(10.0, 50.0))
    elif kind == "park":
        for _ in range(int(rng.poisson(clutter * (x1 - x0) * (y1 - y0) / 80.0)) + 1):
            build.blob(
                np.array([rng.uniform(x0, x1), rng.uniform(y0, y1)]),
                rng.uniform(2.0, 9.0),
                rng.uniform(12.0, 45.0) * clutter,
                occluder=rng.random() < 0.5,
            )
        grass = int(clutter * (x1 - x0) * (y1 - y0) * 0.12)
        build.add(
            np.stack([rng.uniform(x0, x1, grass), rng.uniform(y0, y1, grass)], -1),
            rng.uniform(2.0, 5.0) * rng.lognormal(0.0, 0.7, grass),
            None,
            False,
        )
    elif kind == "car_park":
        yaw = float(rng.choice([0.0, np.pi / 2]))
        length_along_x = yaw != 0.0  # yaw 0: a car's length runs along y
        rows, slots = ((x0, x1), (y0, y1)) if length_along_x else ((y0, y1), (x0, x1))
        occupancy = rng.uniform(0.2, 0.9) * min(parked_density, 1.5) / 1.5
        for row in np.arange(rows[0] + 3.0, rows[1] - 3.0, rng.uniform(6.0, 8.0)):  # rows of cars side by side
            for slot in np.arange(slots[0] + 1.5, slots[1] - 1.5, 2.6):
                if rng.random() < occupancy:
                    centre = np.array([row, slot]) if length_along_x else np.array([slot, row])
                    build.parked_car(centre, yaw + rng.normal(0, 0.04))
        for side in ((x0, y0, x1, y0), (x0, y1, x1, y1)):
            build.wall(np.array(side[:2]), np.array(side[2:]), np.array([0.0, 1.0]), rng.uniform(4, 15), False, 0.8)
    else:
        count = int(clutter * (x1 - x0) * (y1 - y0) * 0.12)
        build.add(
            np.stack([rng.uniform(x0, x1, count), rng.uniform(y0, y1, count)], -1),
            rng.uniform(1.5, 4.0) * rng.lognormal(0.0, 0.7, count),
            None,
            False,
        )
