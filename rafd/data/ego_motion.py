"""Ego poses of whole sequences by radar odometry: estimate them, write ego_poses.csv, compare with true poses.

`rafd-odometry` runs these over a data root (in parallel processes, rafd.data.parallel); training and evaluation
read the written files and never run odometry themselves unless asked (--estimate-poses).
"""

from __future__ import annotations

import functools
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from rafd.data.odometry import estimate_relative_pose
from rafd.data.parallel import run_per_sequence
from rafd.data.poses import POSES_FILE, read_ego_poses, write_ego_poses
from rafd.data.reader import list_frames
from rafd.geometry import compose_poses, relative_pose, wrap_angle


def estimate(seq_dir: Path) -> tuple[list[int], list[str], np.ndarray, np.ndarray, list[float]]:
    """-> (frame numbers, canonical timestamp texts, world poses [N, 3], relative poses [N-1, 3], seconds per pair)."""
    listing = list_frames(seq_dir)
    if len(listing.numbers) < 2:
        raise ValueError(f"{seq_dir} has {len(listing.numbers)} frame(s); odometry needs at least 2")
    relatives, seconds = [], []
    previous = listing.load(0)
    for index in range(1, len(listing.numbers)):
        current = listing.load(index)  # a Cartesian scan (converted from the polar one in polar-only folders)
        start = time.perf_counter()
        relatives.append(estimate_relative_pose(previous, current, listing.resolution))
        seconds.append(time.perf_counter() - start)
        previous = current
    poses = [np.zeros(3)]
    for relative in relatives:
        poses.append(compose_poses(poses[-1], relative))
    return listing.numbers, listing.timestamp_texts, np.stack(poses), np.array(relatives).reshape(-1, 3), seconds


def prepare_poses(seq_dir: Path, out: Path | None, force: bool) -> tuple[str, int, float]:
    """Write one sequence's ego_poses.csv (atomically) -> (status "written" | "skipped", frames, ms per pair)."""
    out = out or seq_dir / POSES_FILE
    if out.exists() and not force:
        return "skipped", 0, 0.0
    numbers, stamps, poses, _, seconds = estimate(seq_dir)
    write_ego_poses(out, numbers, stamps, poses)
    return "written", len(numbers), 1e3 * float(np.mean(seconds))


def pose_errors(seq_dir: Path, numbers: list[int], relatives: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-pair (translation error m, yaw error deg) against SEQ_DIR/ego_poses.csv."""
    truth_table = read_ego_poses(seq_dir / POSES_FILE)
    missing = [n for n in numbers if n not in truth_table]
    if missing:
        raise ValueError(f"{seq_dir / POSES_FILE}: no pose for frame {missing[0]}")
    truth = np.stack([truth_table[n][1] for n in numbers])
    true_relatives = np.stack([relative_pose(truth[k], truth[k - 1]) for k in range(1, len(truth))]).reshape(-1, 3)
    translation = np.hypot(*(relatives[:, :2] - true_relatives[:, :2]).T)
    yaw = np.abs(np.rad2deg(wrap_angle(relatives[:, 2] - true_relatives[:, 2])))
    return translation, yaw


def error_summary(label: str, translation: np.ndarray, yaw: np.ndarray, seconds: list[float]) -> str:
    return (
        f"{label}: {len(translation)} pairs | translation error m mean {translation.mean():.3f} "
        f"p95 {np.percentile(translation, 95):.3f} max {translation.max():.3f} | yaw error deg mean {yaw.mean():.3f} "
        f"p95 {np.percentile(yaw, 95):.3f} max {yaw.max():.3f} | {1e3 * np.mean(seconds):.1f} ms/pair"
    )


def write_poses(
    folders: Sequence[Path], workers: int, force: bool = False, out: Path | None = None, progress: bool = True
) -> tuple[list[tuple[Path, tuple[str, int, float]]], list[str]]:
    """prepare_poses for every folder in `workers` processes (`out`: one sequence's CSV elsewhere) ->
    ([(folder, (status, frames, ms per pair))], ["folder: error"])."""
    job = functools.partial(prepare_poses, out=out, force=force)
    return run_per_sequence(job, list(folders), workers, "odometry", progress=progress)
