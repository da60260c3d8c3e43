"""One simulated drive through a town: world, traffic and sensor stepped frame by frame into scans and labels.

Scan timing: a Navtech scan is a sweep of SCAN_PERIOD seconds, clockwise from straight ahead. Each scatterer is seen
when the beam passes its azimuth, from where the ego is at that moment, and each road user where it is then: moving
things and the static world are smeared by the motion during the sweep, and the sweep's start and end meet in a seam
straight ahead, displaced by the ego's motion during one rotation. A frame's timestamp and pose are those of the
middle of its sweep; each label is where its road user was seen (rafd.sim.vehicles.annotation_box).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from rafd.geometry import RADIATE_RESOLUTION, rotation_matrix
from rafd.scans.polar import to_radiate_polar
from rafd.sim.city import LANE_WIDTH, Street, build_city
from rafd.sim.road import drive_ego, make_route
from rafd.sim.scene import Scatterers
from rafd.sim.sensor import Conditions, Difficulty, NavtechSensor
from rafd.sim.traffic import spawn_traffic
from rafd.sim.vehicles import STRENGTH_RANGE, annotation_box, diffuse_returns, sample_look

logger = logging.getLogger(__name__)

SCAN_PERIOD = 0.2375  # seconds; RADIATE's Navtech delivers ~4.2 scans per second
FINE_STEPS = 4  # samples of the world per scan period (motion within a sweep is interpolated between them)
MIN_LIT_FRACTION = 0.2  # share of a road user's beams in which its nearest return is unshadowed, to be annotated
# ... or, shadowed, a return still as strong as the faintest unshadowed one the simulator draws (STRENGTH_RANGE's
# low end): the sensor renders what is behind an occluder at `shadow` of its power, and annotators box what they see
# (a parked car behind its neighbour in a car park row, a van behind a hedge).
MIN_SHADOWED_STRENGTH = STRENGTH_RANGE[0]
# RADIATE's annotators: a box's rotation is only defined modulo 180 degrees, and within one track the labels flip
# yaw by 180 degrees and exchange width and length (turning by 90 degrees) from frame to frame. Each simulated
# annotation does each independently with these probabilities (0.5 = no preferred labelling at all).
LABEL_FLIP_PROBABILITY = 0.5
LABEL_SWAP_PROBABILITY = 0.5
TURN_PROBABILITY = 0.35  # drives that turn at a junction
EMPTY_STREETS_PROBABILITY = 0.12  # drives without moving traffic
DENSITY_RANGE = (0.04, 1.6)  # moving vehicles per lane per 45 m, log-uniform: from empty to ~10 per 44 m crop


@dataclass(frozen=True)
class SimulatedObject:
    id: int
    class_name: str
    boxes: np.ndarray  # [T, 5] metres in each frame's ego frame; NaN rows where not annotated
    # [T, 2] true ground velocity (m/s) at the moment the beam saw it, in each frame's ego axes (x right, y forward,
    # the frame's pose): the world velocity of its trajectory rotated by -pose yaw; NaN rows where not annotated
    velocities: np.ndarray | None = None


@dataclass(frozen=True)
class SimulatedSequence:
    name: str
    split: str
    seed: int
    resolution: float
    images: list[np.ndarray]  # T x uint8 [S, S]
    timestamps_ns: np.ndarray  # [T] int64 UNIX nanoseconds (middle of each sweep)
    poses: np.ndarray  # [T, 3] true world poses of the radar's ego frame (middle of each sweep)
    objects: list[SimulatedObject]  # only objects annotated in at least one frame
    polar_scans: list[np.ndarray] | None = None  # T x uint8 [576, 400]: the scans in RADIATE's Navtech_Polar layout
    conditions: Conditions | None = None


def frame_times(rng: np.random.Generator, num_frames: int) -> np.ndarray:
    """[T] int64 UNIX nanoseconds: a start between Nov 2019 and Feb 2020 (RADIATE's recording
    period), then ~4 Hz with the Navtech's small period jitter."""
    start = int(rng.integers(1_572_566_400, 1_582_934_400)) * 1_000_000_000 + int(rng.integers(0, 1_000_000_000))
    periods = np.clip(rng.normal(SCAN_PERIOD, 0.004, num_frames - 1), 0.22, 0.26)
    return start + np.concatenate([[0], np.cumsum(np.round(periods * 1e9).astype(np.int64))])


CLUTTER_POINTS = 600  # scattered clutter points per 100 m scan disc at Difficulty.clutter = 1
CLUTTER_POWER = (math.log(8.0), 0.9)  # log-normal (mu, sigma) of a clutter point's power (noise floor = 1)
CLUTTER_BURSTS = 8  # small clutter bursts per 100 m scan disc
BURST_POINTS = (10, 40)  # points per burst (integers in [lo, hi))
BURST_POWER = (math.log(10.0), 0.7)  # log-normal (mu, sigma) of a burst point's power
SCINTILLATION = 0.3  # std of the per-scan log power of world-fixed clutter (aspect changes as the ego moves)


def world_clutter(
    rng: np.random.Generator, bounds: tuple[float, float, float, float], difficulty: Difficulty, persistence: float
) -> tuple[np.ndarray, np.ndarray]:
    """The persistent share of the point clutter (road furniture, litter, small signs), fixed in the world over
    `bounds`: ([N, 2] world metres, [N] power), at the same density per m^2 as _transient_returns draws per scan."""
    x_lo, x_hi, y_lo, y_hi = bounds
    area = (x_hi - x_lo) * (y_hi - y_lo)
    per_m2 = persistence * difficulty.clutter / (math.pi * 100.0**2)
    count = rng.poisson(CLUTTER_POINTS * per_m2 * area)
    xy = [np.stack([rng.uniform(x_lo, x_hi, count), rng.uniform(y_lo, y_hi, count)], -1)]
    power = [rng.lognormal(*CLUTTER_POWER, count)]
    for _ in range(rng.poisson(CLUTTER_BURSTS * per_m2 * area)):
        n = int(rng.integers(*BURST_POINTS))
        xy.append(np.array([rng.uniform(x_lo, x_hi), rng.uniform(y_lo, y_hi)]) + rng.normal(0.0, 1.0, (n, 2)))
        power.append(rng.lognormal(*BURST_POWER, n))
    return np.concatenate(xy), np.concatenate(power)


def _transient_returns(
    rng: np.random.Generator,
    sensor: NavtechSensor,
    difficulty: Difficulty,
    persistence: float,
    ghosts_from: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns that do not persist between scans: the transient 1 - `persistence` share of the scattered clutter
    (spray, birds, multipath speckle) and of the small clutter bursts, and multipath ghosts of vehicles displaced to
    a longer range."""
    azimuths = sensor.config.azimuths
    share = (1.0 - persistence) * difficulty.clutter * (sensor.max_range / 100.0) ** 2
    count = rng.poisson(CLUTTER_POINTS * share)
    az = [rng.uniform(0, azimuths, count)]
    rg = [sensor.max_range * np.sqrt(rng.random(count))]
    pw = [rng.lognormal(*CLUTTER_POWER, count)]
    for _ in range(rng.poisson(CLUTTER_BURSTS * share)):
        n = int(rng.integers(*BURST_POINTS))
        a0, r0 = rng.uniform(0, azimuths), rng.uniform(5.0, sensor.max_range)
        az.append(a0 + rng.normal(0, 1.0, n))
        rg.append(r0 + rng.normal(0, 1.2, n))
        pw.append(rng.lognormal(*BURST_POWER, n))
    for g_az, g_rg, g_pw in ghosts_from:
        if rng.random() < min(1.0, 0.3 * difficulty.ghosts):
            az.append(g_az + rng.uniform(-2.5, 2.5))
            rg.append(g_rg + rng.uniform(3.0, 15.0))
            pw.append(g_pw * rng.uniform(0.1, 0.35) * min(difficulty.ghosts, 3.0))
    az_all, rg_all = np.concatenate(az), np.concatenate(rg)
    keep = (rg_all > 1.0) & (rg_all < sensor.max_range)
    return np.mod(az_all[keep], azimuths), rg_all[keep], np.concatenate(pw)[keep]


def ambiguous_labels(boxes: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """[..., 5] boxes -> the same rectangles labelled as RADIATE's annotators do: yaw + 180 degrees and/or width and
    length exchanged (yaw + 90 degrees), each independently per box (LABEL_*_PROBABILITY)."""
    boxes = np.array(boxes, dtype=np.float64)
    flip = rng.random(boxes.shape[:-1]) < LABEL_FLIP_PROBABILITY
    swap = rng.random(boxes.shape[:-1]) < LABEL_SWAP_PROBABILITY
    boxes[..., 4] += np.where(flip, np.pi, 0.0) + np.where(swap, np.pi / 2.0, 0.0)
    width = boxes[..., 2].copy()
    boxes[..., 2] = np.where(swap, boxes[..., 3], width)
    boxes[..., 3] = np.where(swap, width, boxes[..., 3])
    boxes[..., 4] = (boxes[..., 4] + np.pi) % (2.0 * np.pi) - np.pi
    return boxes


def _interpolate(times: np.ndarray, values: np.ndarray, at: np.ndarray | float, angle_column: int | None = None):
    """Linear interpolation of [F, D] samples at times [F]; angle_column is unwrapped first."""
    values = np.array(values, dtype=np.float64)
    if angle_column is not None:
        values[:, angle_column] = np.unwrap(values[:, angle_column])
    at = np.atleast_1d(np.asarray(at, np.float64))
    return np.stack([np.interp(at, times, values[:, d]) for d in range(values.shape[1])], -1)


def trajectory_velocity(times: np.ndarray, boxes: np.ndarray, at: float) -> np.ndarray:
    """[F] times and [F, 5] world boxes of a piecewise-linear trajectory (what _interpolate reads) -> [2] its world
    velocity (m/s) at time `at`: the slope of the segment holding it, exactly."""
    segment = int(np.clip(np.searchsorted(times, at, side="right") - 1, 0, len(times) - 2))
    return (boxes[segment + 1, :2] - boxes[segment, :2]) / (times[segment + 1] - times[segment])


def _to_ego(poses: np.ndarray, points: np.ndarray) -> np.ndarray:
    """World points [N, 2] -> ego coordinates under poses [N, 3] (one pose per point)."""
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    d = points - poses[:, :2]
    return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], -1)


def _sweep_fraction(xy: np.ndarray) -> np.ndarray:
    """[N, 2] ego points -> [N] fraction of the sweep (clockwise from straight ahead) at which the beam sees them."""
    return np.mod(np.arctan2(xy[:, 0], xy[:, 1]), 2 * np.pi) / (2 * np.pi)


def sweep_positions(start: np.ndarray, end: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ego-frame positions of points at the sweep's start [N, 2] and end [N, 2] -> (where the beam sees them [N, 2],
    the sweep fraction then [N]); two fixed-point steps of linear motion within the sweep."""
    fraction = _sweep_fraction(start)
    for _ in range(2):
        seen = start + fraction[:, None] * (end - start)
        fraction = _sweep_fraction(seen)
    return start + fraction[:, None] * (end - start), fraction


def visible_beams(echoes, owners: int, azimuths: int) -> tuple[np.ndarray, np.ndarray]:
    """Per road user: (beams in which its nearest return is outside every other occluder's shadow, beams it occupies).
    Its own far side is shadowed by its near side, which is what partly filled returns are; that is not occlusion."""
    mine = np.flatnonzero(echoes.owner >= 0)
    if len(mine) == 0:
        return np.zeros(owners, np.int64), np.zeros(owners, np.int64)
    keys = echoes.owner[mine] * azimuths + np.minimum(echoes.azimuth[mine].astype(np.int64), azimuths - 1)
    order = np.lexsort((echoes.ranges[mine], keys))  # by beam key, nearest first
    first = order[np.r_[True, keys[order][1:] != keys[order][:-1]]]  # each (owner, beam)'s nearest return
    owner = echoes.owner[mine][first]
    return (np.bincount(owner[echoes.lit[mine][first]], minlength=owners), np.bincount(owner, minlength=owners))


def annotator_sees(lit: np.ndarray, seen: np.ndarray, strength: np.ndarray, shadow: float) -> np.ndarray:
    """Per road user: is it annotated? lit / seen: beams in which its nearest return is unshadowed / that it occupies
    (visible_beams); strength: its Look.strength. Either enough of it is unshadowed, or its return as rendered (each
    shadowed beam at `shadow` of the power) is still as strong as the faintest unshadowed road user's."""
    beams = np.maximum(seen, 1)
    rendered = strength * (lit + shadow * (beams - lit)) / beams
    return (seen > 0) & ((lit >= MIN_LIT_FRACTION * beams) | (rendered >= MIN_SHADOWED_STRENGTH))


def run_simulation(
    seed: int,
    num_frames: int,
    split: str,
    size: int,
    difficulty: Difficulty,
    name: str,
    resolution: float = RADIATE_RESOLUTION,
    ambiguous: bool = True,
    weather: str | None = None,
) -> SimulatedSequence:
    """Simulate `num_frames` scans of size x size pixels deterministically from `seed`. `ambiguous` labels boxes as
    RADIATE's annotators do (ambiguous_labels); False keeps width across and yaw along each road user's travel.
    `weather` ("clear" | "fog" | "rain") forces the drive's weather; None draws it (Conditions.sample)."""
    if num_frames < 1:
        raise ValueError(f"num_frames must be >= 1, got {num_frames}")
    if size < 16 or size % 2:
        raise ValueError(f"size must be an even number of pixels >= 16, got {size}")
    rng = np.random.default_rng(seed)
    label_rng = np.random.default_rng([seed, 1])  # its own generator: the scans do not depend on the labelling
    sensor = NavtechSensor(size, resolution)
    conditions = Conditions.sample(rng, weather)
    stamps = frame_times(rng, num_frames)
    times = (stamps - stamps[0]) / 1e9
    fine = np.arange(-SCAN_PERIOD, times[-1] + 1.5 * SCAN_PERIOD, SCAN_PERIOD / FINE_STEPS)
    view = sensor.max_range
    reach = 15.0 * (fine[-1] - fine[0]) + 30.0  # farthest the ego can drive
    lanes = int(rng.choice([1, 2], p=[0.7, 0.3]))
    ego_offset = LANE_WIDTH * (int(rng.integers(lanes)) + 0.5)
    ego_street = Street(axis=1, position=ego_offset, lanes=lanes, pavement=float(rng.uniform(2.0, 4.5)))
    density = 0.0 if rng.random() < EMPTY_STREETS_PROBABILITY else math.exp(rng.uniform(*np.log(DENSITY_RANGE)))
    parked_density = float(rng.uniform(0.0, 1.5))
    city = build_city(
        rng,
        (-view - reach - 60.0, view + reach + 60.0, -view - 60.0, view + reach + 60.0),
        ego_street,
        difficulty.clutter,
        parked_density,
    )
    turn, junction = 0, 0.0
    ahead = [st.position for st in city.y_streets if 12.0 < st.position < reach - 15.0]
    if ahead and rng.random() < TURN_PROBABILITY:
        turn, junction = int(rng.choice([-1, 1])), float(rng.choice(ahead))
    route = make_route(
        ego_street.position,
        -view - 100.0,
        reach + view + 100.0,
        lanes,
        turn,
        junction,
        radius=float(rng.uniform(7.0, 14.0)),
    )
    ego = drive_ego(rng, route, fine, ego_offset)
    agents = spawn_traffic(rng, city, route, fine, ego.s, ego_offset, view, density)
    looks = [sample_look(rng, agent.class_name, conditions.vehicle_gain) for agent in agents]
    strengths = np.array([look.strength for look in looks])
    world = city.scatterers
    clutter_xy, clutter_power = world_clutter(rng, city.bounds, difficulty, conditions.clutter_persistence)
    half_extent = size / 2.0 * resolution
    azimuth_bin = 2.0 * math.pi / sensor.config.azimuths
    truth = np.full((len(agents), num_frames, 5), np.nan)
    velocities = np.full((len(agents), num_frames, 2), np.nan)  # true ground velocity, each frame's ego axes
    images, polar_scans, poses = [], [], _interpolate(fine, ego.poses, times, angle_column=2)
    for t in range(num_frames):
        sweep = (times[t] - SCAN_PERIOD / 2.0, times[t] + SCAN_PERIOD / 2.0)
        ego_start, ego_end = _interpolate(fine, ego.poses, np.array(sweep), angle_column=2)
        near = np.hypot(*(world.xy - poses[t, :2]).T) < view + 5.0
        static = world.subset(near)
        seen, _ = sweep_positions(
            _to_ego(np.broadcast_to(ego_start, (len(static), 3)), static.xy),
            _to_ego(np.broadcast_to(ego_end, (len(static), 3)), static.xy),
        )
        turn_by = rotation_matrix(-poses[t, 2])  # normals: the world's orientation in this frame's ego axes
        parts = [Scatterers(seen, static.amplitude, static.normal @ turn_by.T, static.occluder, static.owner)]
        ego_boxes = np.full((len(agents), 5), np.nan)
        ego_velocities = np.full((len(agents), 2), np.nan)
        frame_axes = rotation_matrix(-poses[t, 2])  # world -> this frame's ego axes
        for k, agent in enumerate(agents):
            at_start, at_end = _interpolate(fine, agent.boxes, np.array(sweep), angle_column=4)
            if min(np.hypot(*(at_start[:2] - ego_start[:2])), np.hypot(*(at_end[:2] - ego_end[:2]))) > view + 15.0:
                continue
            _, fraction = sweep_positions(
                _to_ego(ego_start[None], at_start[None, :2]), _to_ego(ego_end[None], at_end[None, :2])
            )
            moment = sweep[0] + fraction[0] * SCAN_PERIOD
            box = _interpolate(fine, agent.boxes, moment, angle_column=4)[0]
            pose = _interpolate(fine, ego.poses, moment, angle_column=2)[0]
            ego_boxes[k, :2] = _to_ego(pose[None], box[None, :2])[0]
            ego_boxes[k, 2:4] = box[2:4]
            ego_boxes[k, 4] = (box[4] - pose[2] + math.pi) % (2 * math.pi) - math.pi
            ego_velocities[k] = frame_axes @ trajectory_velocity(fine, agent.boxes, moment)
            parts.append(diffuse_returns(ego_boxes[k], looks[k], rng, k, azimuth_bin, sensor.config.range_bin))
        echoes = sensor.illuminate(Scatterers.concat(parts), conditions)
        lit, seen_count = visible_beams(echoes, len(agents), sensor.config.azimuths)
        ghosts_from = []
        for owner in np.flatnonzero(seen_count > 0):
            own = echoes.owner == owner
            ghosts_from.append((echoes.azimuth[own], echoes.ranges[own], echoes.power[own]))
        t_az, t_rg, t_pw = _transient_returns(rng, sensor, difficulty, conditions.clutter_persistence, ghosts_from)
        # World-fixed clutter: seen where the sweep finds it, scintillating from scan to scan; like the transient
        # clutter it is added in the polar domain (no facing, occlusion or range loss: calibrated as it is seen).
        close = np.hypot(*(clutter_xy - poses[t, :2]).T) < view + 5.0
        nearby = clutter_xy[close]
        clutter_seen, _ = sweep_positions(
            _to_ego(np.broadcast_to(ego_start, (len(nearby), 3)), nearby),
            _to_ego(np.broadcast_to(ego_end, (len(nearby), 3)), nearby),
        )
        c_az, c_rg = sensor.polar_coordinates(clutter_seen)
        c_pw = clutter_power[close] * rng.lognormal(0.0, SCINTILLATION, len(c_rg))
        inside = (c_rg > 1.0) & (c_rg < sensor.max_range)
        t_az, t_rg, t_pw = (
            np.concatenate([t_az, c_az[inside]]),
            np.concatenate([t_rg, c_rg[inside]]),
            np.concatenate([t_pw, c_pw[inside]]),
        )
        signal = sensor.accumulate(
            np.concatenate([echoes.azimuth, t_az]),
            np.concatenate([echoes.ranges, t_rg]),
            np.concatenate([echoes.power, t_pw]),
            np.concatenate([echoes.diffuse, np.zeros(len(t_az), bool)]),
        )
        received = sensor.receive(signal, rng, difficulty, conditions)
        images.append(sensor.to_cartesian(received))
        polar_scans.append(to_radiate_polar(received.T, sensor.polar_conventions))
        # Annotated: centre inside the image and the scan disc, and seen by the annotator (annotator_sees).
        in_view = (
            np.isfinite(ego_boxes[:, 0])
            & (np.abs(ego_boxes[:, 0]) < half_extent)
            & (np.abs(ego_boxes[:, 1]) < half_extent)
            & (np.hypot(ego_boxes[:, 0], ego_boxes[:, 1]) < sensor.max_range)
            & annotator_sees(lit, seen_count, strengths, sensor.config.shadow)
        )
        for i in np.flatnonzero(in_view):  # agent indices (numpy integers; `k` above is an int)
            truth[i, t] = annotation_box(
                ego_boxes[i], agents[i].class_name, looks[i], label_rng, sensor.beam_sigma_rad, sensor.range_sigma_m
            )
            velocities[i, t] = ego_velocities[i]
    if ambiguous:
        truth = ambiguous_labels(truth, label_rng)
    objects = [
        SimulatedObject(agent.id, agent.class_name, truth[k], velocities[k])
        for k, agent in enumerate(agents)
        if np.isfinite(truth[k, :, 0]).any()
    ]
    logger.info(
        "simulated %s: %d frames, %d annotated objects of %d road users (%s, density %.2f)",
        name,
        num_frames,
        len(objects),
        len(agents),
        conditions.weather,
        density,
    )
    return SimulatedSequence(name, split, seed, resolution, images, stamps, poses, objects, polar_scans, conditions)
