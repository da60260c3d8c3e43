"""ego_poses.csv: the ego's world pose per radar frame (our addition to RADIATE's sequence folders).

Format (UTF-8 CSV, one header line, one row per radar frame, rows in frame order):

    frame,timestamp,x,y,yaw
    1,1574859771.744660272,0.0,0.0,0.0

- frame: RADIATE frame number (the N of Navtech_Cartesian/00000N.png), unique, increasing.
- timestamp: the frame's UNIX time in seconds, as in Navtech_Cartesian.txt.
- x, y: metres, yaw: radians, of the radar's ego frame (x right, y forward) in one fixed world frame
  per sequence: world = R(yaw) @ ego + (x, y) (rafd.geometry's pose convention). The world frame is
  arbitrary (the simulator's road frame, or the first frame for odometry); only relative poses matter.

Written by the simulator (true poses) and by `rafd-odometry SEQ_DIR` (poses estimated from the scans).
"""

from __future__ import annotations

import csv
import logging
import math
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

POSES_FILE = "ego_poses.csv"
POSES_HEADER = ("frame", "timestamp", "x", "y", "yaw")
POSE_TIMESTAMP_TOLERANCE = 1e-3  # seconds: ego_poses.csv rows must carry their frame's timestamp


def _format_timestamp(value: float | str) -> str:
    """Seconds with nanosecond digits (RADIATE's style). A string (e.g. the text of Navtech_Cartesian.txt) is
    written as it is, so no digit is lost; a float64 carries ~0.2 us at today's UNIX times."""
    if isinstance(value, str):
        text = value.strip()
        if not math.isfinite(float(text)):
            raise ValueError(f"timestamp {value!r} is not finite")
        return text
    return f"{float(value):.9f}"


def write_ego_poses(
    path: str | Path, frames: Sequence[int] | np.ndarray, timestamps: Sequence[float | str], poses: np.ndarray
) -> Path:
    """Write `frames` (N frame numbers), `timestamps` (N seconds: floats, or strings written verbatim) and
    `poses` [N, 3] to `path` atomically (temporary file + rename)."""
    path = Path(path)
    frames = [int(f) for f in frames]
    stamp_texts = [_format_timestamp(t if isinstance(t, str) else float(t)) for t in timestamps]
    stamps = np.array([float(t) for t in stamp_texts], dtype=np.float64)
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 2 or poses.shape[1] != 3:
        raise ValueError(f"poses must be [N, 3], got shape {poses.shape}")
    if not (len(frames) == len(stamps) == len(poses)):
        raise ValueError(
            f"frames ({len(frames)}), timestamps ({len(stamps)}) and poses ({len(poses)}) differ in length"
        )
    if any(b <= a for a, b in zip(frames, frames[1:])):
        raise ValueError("frame numbers must be strictly increasing")
    if not (np.all(np.isfinite(poses)) and np.all(np.isfinite(stamps))):
        raise ValueError("poses and timestamps must be finite")
    temporary = path.with_name(f".{path.name}.tmp{os.getpid()}")
    with temporary.open("w", newline="") as handle:
        writer = csv.writer(handle, lineterminator="\n")
        writer.writerow(POSES_HEADER)
        for frame, stamp, pose in zip(frames, stamp_texts, poses):
            # repr() round-trips a float64 exactly.
            writer.writerow([frame, stamp, *(repr(float(v)) for v in pose)])
    os.replace(temporary, path)
    return path


def read_ego_poses(path: str | Path) -> dict[int, tuple[float, np.ndarray]]:
    """`path` -> {frame number: (timestamp seconds, pose [3] float64)}. Raises FileNotFoundError when the
    file is missing and ValueError naming the file and line for anything malformed."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"ego pose file {path} not found")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as error:
        raise ValueError(f"{path}: cannot read the ego pose file ({error})") from error
    rows = list(csv.reader(text.splitlines()))
    if not rows or tuple(cell.strip() for cell in rows[0]) != POSES_HEADER:
        found = ",".join(rows[0]) if rows else "an empty file"
        raise ValueError(f"{path}: expected the header {','.join(POSES_HEADER)!r}, found {found!r}")
    poses: dict[int, tuple[float, np.ndarray]] = {}
    previous = None
    for line_number, row in enumerate(rows[1:], start=2):
        if not row or all(not cell.strip() for cell in row):
            continue  # a blank line (e.g. at the end)
        if len(row) != len(POSES_HEADER):
            raise ValueError(f"{path}:{line_number}: expected {len(POSES_HEADER)} columns, got {len(row)}: {row!r}")
        try:
            frame = int(row[0])
            values = [float(cell) for cell in row[1:]]
        except ValueError as error:
            raise ValueError(f"{path}:{line_number}: not a number in {row!r} ({error})") from error
        if not all(math.isfinite(v) for v in values):
            raise ValueError(f"{path}:{line_number}: non-finite value in {row!r}")
        if frame in poses:
            raise ValueError(f"{path}:{line_number}: frame {frame} appears twice")
        if previous is not None and frame < previous:
            raise ValueError(f"{path}:{line_number}: frame {frame} after frame {previous}; rows must be in frame order")
        previous = frame
        poses[frame] = (values[0], np.array(values[1:], dtype=np.float64))
    if not poses:
        raise ValueError(f"{path}: no pose rows")
    return poses


def read_frame_poses(path: Path, numbers: list[int], stamps: list[float]) -> np.ndarray:
    """ego_poses.csv -> [N, 3] poses of the frames on disk (`numbers`, with the scans' timestamps `stamps`); ValueError
    naming the file when a frame has no row or its row carries another timestamp (a pose file of another sequence)."""
    table = read_ego_poses(path)
    missing = [n for n in numbers if n not in table]
    if missing:
        raise ValueError(f"{path}: no pose for {len(missing)} frames on disk (first: frame {missing[0]})")
    for number, stamp in zip(numbers, stamps):
        if abs(table[number][0] - stamp) > POSE_TIMESTAMP_TOLERANCE:
            raise ValueError(
                f"{path}: frame {number} has timestamp {table[number][0]:.6f}, "
                f"the scans' timestamp file says {stamp:.6f} (pose file of another sequence?)"
            )
    extra = len(table) - len(numbers)
    if extra:
        log.debug("%s: %d pose rows for frames not on disk ignored", path, extra)
    return np.stack([table[n][1] for n in numbers])
