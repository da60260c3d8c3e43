"""Ego poses of whole sequences by radar odometry: estimate them, write ego_poses.csv, compare with true poses.

`rafd-odometry` runs these over a data root (in parallel processes, rafd.data.parallel); training and evaluation
read the written files and never run odometry themselves unless asked (`rafd eval --estimate-poses`, `rafd train
... data.estimate_poses=true`).
"""

from __future__ import annotations

import functools
import time
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np

from rafd.data.folders import FrameList, list_frames
from rafd.data.parallel import run_per_sequence
from rafd.data.poses import POSES_FILE, write_ego_poses
from rafd.data.reader import read_sequence
from rafd.geometry import RADIATE_RESOLUTION, compose_poses, relative_pose, wrap_angle
from rafd.odometry.registration import GAP_PERIODS, OdometryStream, SweepTiming
from rafd.scans.native import NativeSource, read_native_scan, to_cartesian


def scan_and_timing(listing: FrameList, index: int) -> tuple[np.ndarray, SweepTiming | None]:
    """A frame's Cartesian scan and, for native scans, its sweep's own timing (None: uniform, from the timestamps)."""
    if isinstance(listing.polar, NativeSource):
        scan = read_native_scan(listing.image_paths[index], listing.polar.fmt)
        image = to_cartesian(scan, listing.polar.size, listing.polar.resolution)
        return image, SweepTiming.of_native(scan.timestamps_us, scan.azimuths)
    return listing.load(index), None  # a Cartesian scan (converted from the polar one in polar-only folders)


def _bag_scans(bag: Path) -> tuple[list[int], list[float], list[str], Iterator[tuple[np.ndarray, SweepTiming | None]]]:
    """A bag's frames for odometry: numbers, seconds, texts, and (Cartesian scan, sweep timing) read in one pass."""
    from rafd.ros.sequence import bag_frames, cartesian_of, native_scan_of

    topic, listed = bag_frames(bag)
    numbers = list(range(1, len(listed) + 1))
    texts = [f"{stamp // 1_000_000_000}.{stamp % 1_000_000_000:09d}" for _, stamp in listed]

    def scans() -> Iterator[tuple[np.ndarray, SweepTiming | None]]:
        from rafd.ros.reader import read_scans

        for _, scan in read_scans(topic):
            timing = None
            if scan.layout == "native":
                native = native_scan_of(scan)
                timing = SweepTiming.of_native(native.timestamps_us, native.azimuths)
            yield cartesian_of(scan), timing

    return numbers, [stamp / 1e9 for _, stamp in listed], texts, scans()


def estimate(seq_dir: Path) -> tuple[list[int], list[str], np.ndarray, np.ndarray, list[float]]:
    """-> (frame numbers, canonical timestamp texts, world poses [N, 3], relative poses [N-1, 3], seconds per pair).
    Motion-compensated from the scans' timestamps (rafd.odometry.registration.OdometryStream). A ROS 2 bag's scans are
    read in one pass, with each native scan's own sweep timing."""
    from rafd.ros.sequence import is_bag

    if is_bag(seq_dir):
        numbers, seconds_of, texts, scans = _bag_scans(seq_dir)
        if len(numbers) < 2:
            raise ValueError(f"{seq_dir} has {len(numbers)} scan(s); odometry needs at least 2")
        return _run(numbers, texts, seconds_of, scans, RADIATE_RESOLUTION)
    listing = list_frames(seq_dir)
    if len(listing.numbers) < 2:
        raise ValueError(f"{seq_dir} has {len(listing.numbers)} frame(s); odometry needs at least 2")
    scans = (scan_and_timing(listing, index) for index in range(len(listing.numbers)))
    return _run(listing.numbers, listing.timestamp_texts, listing.timestamps, scans, listing.resolution)


def _run(
    numbers: list[int],
    texts: list[str],
    timestamps: Sequence[float],
    scans: Iterable[tuple[np.ndarray, SweepTiming | None]],
    resolution: float,
) -> tuple[list[int], list[str], np.ndarray, np.ndarray, list[float]]:
    relatives, seconds = [], []
    stream = OdometryStream(resolution)
    for index, (image, timing) in enumerate(scans):
        start = time.perf_counter()
        relative = stream.add(image, timestamps[index], timing)
        if relative is not None:
            relatives.append(relative)
            seconds.append(time.perf_counter() - start)
    poses = [np.zeros(3)]
    for relative in relatives:
        poses.append(compose_poses(poses[-1], relative))
    return numbers, texts, np.stack(poses), np.array(relatives).reshape(-1, 3), seconds


def prepare_poses(seq_dir: Path, out: Path | None, force: bool) -> tuple[str, int, float]:
    """Write one sequence's ego_poses.csv (atomically; a bag's beside it, rafd.ros.sequence.poses_file) -> (status
    "written" | "skipped", frames, ms per pair)."""
    from rafd.ros.sequence import is_bag, poses_file

    out = out or (poses_file(seq_dir) if is_bag(seq_dir) else seq_dir / POSES_FILE)
    if out.exists() and not force:
        return "skipped", 0, 0.0
    numbers, stamps, poses, _, seconds = estimate(seq_dir)
    write_ego_poses(out, numbers, stamps, poses)
    return "written", len(numbers), 1e3 * float(np.mean(seconds))


def signed_errors(seq_dir: Path, numbers: list[int], relatives: np.ndarray) -> np.ndarray:
    """[N-1, 3] estimated minus true relative pose per pair (x m, y m, yaw rad wrapped), in the previous ego frame."""
    sequence = read_sequence(seq_dir, estimate_poses=False)
    if sequence.pose_source != "file" or sequence.poses is None:
        raise ValueError(f"{seq_dir}: no true poses to compare with ({POSES_FILE} or a native folder's ground truth)")
    by_number = sequence.poses_by_frame()
    missing = [n for n in numbers if n not in by_number]
    if missing:
        raise ValueError(f"{seq_dir}: no true pose for frame {missing[0]}")
    truth = np.stack([by_number[n] for n in numbers])
    true_relatives = np.stack([relative_pose(truth[k], truth[k - 1]) for k in range(1, len(truth))]).reshape(-1, 3)
    error = np.asarray(relatives, np.float64).reshape(-1, 3) - true_relatives
    error[:, 2] = wrap_angle(error[:, 2])
    return error


def consecutive_pairs(timestamp_texts: Sequence[str]) -> np.ndarray:
    """[N-1] bool: the pairs of scans one period apart (not across a gap in the recording, GAP_PERIODS)."""
    dt = np.diff(np.array([float(text) for text in timestamp_texts]))
    return dt <= GAP_PERIODS * float(np.median(dt)) if len(dt) else np.zeros(0, bool)


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
