"""One simulated drive: world, traffic and sensor stepped frame by frame into scans and ground truth."""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rafd.geometry import RADIATE_RESOLUTION, invert_pose, rotation_matrix, transform_boxes
from rafd.polar import to_radiate_polar
from rafd.sim.road import LANE_WIDTH, drive_ego, make_road
from rafd.sim.scene import Scatterers, body_model, build_static_world
from rafd.sim.sensor import Difficulty, NavtechSensor
from rafd.sim.traffic import spawn_traffic

logger = logging.getLogger(__name__)

SCAN_PERIOD = 0.2375  # seconds; RADIATE's Navtech delivers ~4.2 scans per second
MIN_VISIBLE_POINTS = 3  # unshadowed outline points needed for an object to be annotated
# RADIATE's annotators: a box's rotation is only defined modulo 180 degrees, and within one track the labels flip
# yaw by 180 degrees and exchange width and length (turning by 90 degrees) from frame to frame. Each simulated
# annotation does each independently with these probabilities (0.5 = no preferred labelling at all).
LABEL_FLIP_PROBABILITY = 0.5
LABEL_SWAP_PROBABILITY = 0.5


@dataclass(frozen=True)
class SimulatedObject:
    id: int
    class_name: str
    boxes: np.ndarray  # [T, 5] metres in each frame's ego frame; NaN rows where not annotated


@dataclass(frozen=True)
class SimulatedSequence:
    name: str
    split: str
    seed: int
    resolution: float
    images: list[np.ndarray]  # T x uint8 [S, S]
    timestamps_ns: np.ndarray  # [T] int64 UNIX nanoseconds
    poses: np.ndarray  # [T, 3] true world poses of the radar's ego frame
    objects: list[SimulatedObject]  # only objects annotated in at least one frame
    polar_scans: list[np.ndarray] | None = None  # T x uint8 [576, 400]: the scans in RADIATE's Navtech_Polar layout


def frame_times(rng: np.random.Generator, num_frames: int) -> np.ndarray:
    """[T] int64 UNIX nanoseconds: a start between Nov 2019 and Feb 2020 (RADIATE's recording
    period), then ~4 Hz with the Navtech's small period jitter."""
    start = int(rng.integers(1_572_566_400, 1_582_934_400)) * 1_000_000_000 + int(rng.integers(0, 1_000_000_000))
    periods = np.clip(rng.normal(SCAN_PERIOD, 0.004, num_frames - 1), 0.22, 0.26)
    return start + np.concatenate([[0], np.cumsum(np.round(periods * 1e9).astype(np.int64))])


def _transient_returns(
    rng: np.random.Generator, sensor: NavtechSensor, difficulty: Difficulty, ghosts_from: list[tuple[np.ndarray, np.ndarray, np.ndarray]]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns that do not persist between scans: scattered clutter (spray, birds, multipath speckle),
    small clutter bursts, and multipath ghosts of vehicles displaced to a longer range."""
    azimuths = sensor.config.azimuths
    count = rng.poisson(600 * difficulty.clutter)
    az = [rng.uniform(0, azimuths, count)]
    rg = [sensor.max_range * np.sqrt(rng.random(count))]
    pw = [rng.lognormal(np.log(8.0), 0.9, count)]
    for _ in range(rng.poisson(8 * difficulty.clutter)):
        n = int(rng.integers(10, 40))
        a0, r0 = rng.uniform(0, azimuths), rng.uniform(5.0, sensor.max_range)
        az.append(a0 + rng.normal(0, 1.0, n))
        rg.append(r0 + rng.normal(0, 1.2, n))
        pw.append(rng.lognormal(np.log(10.0), 0.7, n))
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


def run_simulation(
    seed: int, num_frames: int, split: str, size: int, difficulty: Difficulty, name: str,
    resolution: float = RADIATE_RESOLUTION, ambiguous: bool = True,
) -> SimulatedSequence:
    """Simulate `num_frames` scans of size x size pixels deterministically from `seed`. `ambiguous` labels boxes as
    RADIATE's annotators do (ambiguous_labels); False keeps width across and yaw along each road user's travel."""
    if num_frames < 1:
        raise ValueError(f"num_frames must be >= 1, got {num_frames}")
    if size < 16 or size % 2:
        raise ValueError(f"size must be an even number of pixels >= 16, got {size}")
    rng = np.random.default_rng(seed)
    sensor = NavtechSensor(size, resolution)
    stamps = frame_times(rng, num_frames)
    times = (stamps - stamps[0]) / 1e9
    view = sensor.max_range
    lane = LANE_WIDTH / 2.0
    road = make_road(rng, -view - 250.0, 16.0 * times[-1] + view + 250.0, lane)
    ego = drive_ego(rng, road, times, lane)
    agents = spawn_traffic(rng, road, times, ego.s, lane, view, density=1.0)
    world = build_static_world(rng, road, ego.s.min() - view - 15.0, ego.s.max() + view + 15.0, difficulty.clutter)
    bodies = [body_model(rng, agent, index) for index, agent in enumerate(agents)]
    world_boxes = np.stack([agent.world_boxes(road) for agent in agents]) if agents else np.zeros((0, num_frames, 5))
    half_extent = size / 2.0 * resolution
    truth = np.full((len(agents), num_frames, 5), np.nan)
    images, polar_scans = [], []
    for t in range(num_frames):
        to_ego = invert_pose(ego.poses[t])
        rotation, translation = rotation_matrix(to_ego[2]), to_ego[:2]
        near = np.hypot(*(world.xy - ego.poses[t, :2]).T) < view + 2.0
        parts = [Scatterers(world.xy[near], world.amplitude[near], world.normal[near], world.occluder[near], world.owner[near]).transformed(rotation, translation)]
        ego_boxes = transform_boxes(to_ego, world_boxes[:, t]) if agents else np.zeros((0, 5))
        close = np.flatnonzero(np.hypot(ego_boxes[:, 0], ego_boxes[:, 1]) < view + 15.0)
        for k in close:
            box = ego_boxes[k]
            parts.append(bodies[k].local.transformed(rotation_matrix(box[4]), box[:2]))
        echoes = sensor.illuminate(Scatterers.concat(parts))
        lit_owner = echoes.owner[echoes.lit & (echoes.owner >= 0)]
        lit_counts = np.bincount(lit_owner, minlength=len(agents))
        ghosts_from = []
        for k in np.flatnonzero(lit_counts >= MIN_VISIBLE_POINTS):
            mine = echoes.owner == k
            ghosts_from.append((echoes.azimuth[mine], echoes.ranges[mine], echoes.power[mine]))
        t_az, t_rg, t_pw = _transient_returns(rng, sensor, difficulty, ghosts_from)
        signal = sensor.accumulate(np.concatenate([echoes.azimuth, t_az]), np.concatenate([echoes.ranges, t_rg]), np.concatenate([echoes.power, t_pw]))
        received = sensor.receive(signal, rng, difficulty)  # [A, R] grey levels
        images.append(sensor.to_cartesian(received))
        polar_scans.append(to_radiate_polar(received.T, sensor.polar_conventions))
        # Annotated: centre inside the image and the scan disc, and enough of the outline lit.
        in_view = (
            (np.abs(ego_boxes[:, 0]) < half_extent)
            & (np.abs(ego_boxes[:, 1]) < half_extent)
            & (np.hypot(ego_boxes[:, 0], ego_boxes[:, 1]) < sensor.max_range)
            & (lit_counts >= MIN_VISIBLE_POINTS)
        )
        truth[in_view, t] = ego_boxes[in_view]
    if ambiguous:  # its own generator: the scans do not depend on the labelling
        truth = ambiguous_labels(truth, np.random.default_rng([seed, 1]))
    objects = [
        SimulatedObject(agent.id, agent.class_name, truth[k])
        for k, agent in enumerate(agents)
        if np.isfinite(truth[k, :, 0]).any()
    ]
    logger.info("simulated %s: %d frames, %d annotated objects of %d road users", name, num_frames, len(objects), len(agents))
    return SimulatedSequence(name, split, seed, resolution, images, stamps, ego.poses, objects, polar_scans)
