"""Write a simulated sequence in RADIATE's on-disk layout (+ our ego_poses.csv with the true poses and
annotations/velocities.json with the road users' true ground velocities; optionally the polar scans as Navtech_Polar/ +
Navtech_Polar.txt, RADIATE's layout and bin size)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from rafd.data.folders import VELOCITIES_FILE
from rafd.data.poses import write_ego_poses
from rafd.geometry import box_to_radiate
from rafd.sim.sequence import SimulatedSequence


def format_timestamp(nanoseconds: int) -> str:
    """UNIX nanoseconds -> RADIATE's 'seconds.nanoseconds' text, exact (no float rounding)."""
    return f"{int(nanoseconds) // 1_000_000_000}.{int(nanoseconds) % 1_000_000_000:09d}"


def annotations_json(sequence: SimulatedSequence) -> list[dict]:
    """RADIATE annotations: one entry per object, bboxes[k] for frame k + 1, [] where absent."""
    size = sequence.images[0].shape[0]
    entries = []
    for obj in sequence.objects:
        bboxes: list = []
        for box in obj.boxes:
            if np.isfinite(box[0]):
                position, rotation = box_to_radiate(box, image_size=size, resolution=sequence.resolution)
                bboxes.append({"position": position, "rotation": rotation})
            else:
                bboxes.append([])
        entries.append({"id": int(obj.id), "class_name": obj.class_name, "bboxes": bboxes})
    return entries


def velocities_json(sequence: SimulatedSequence) -> list[dict]:
    """The true ground velocities beside annotations.json: one entry per object, velocities[k] = [vx, vy] m/s for
    frame k + 1 in that frame's ego axes (x right, y forward; ego motion removed), [] where it is not annotated."""
    entries = []
    for obj in sequence.objects:
        if obj.velocities is None:
            continue
        velocities: list = [
            [round(float(v[0]), 4), round(float(v[1]), 4)] if np.isfinite(v).all() else [] for v in obj.velocities
        ]
        entries.append({"id": int(obj.id), "velocities": velocities})
    return entries


def _write_poses(path: Path, sequence: SimulatedSequence) -> None:
    """The true poses, with the timestamps' exact nanosecond texts (rafd.data.poses: one writer for every path)."""
    frames = np.arange(1, len(sequence.images) + 1)
    write_ego_poses(path, frames, [format_timestamp(stamp) for stamp in sequence.timestamps_ns], sequence.poses)


def _write_scans(out_dir: Path, name: str, scans: list[np.ndarray], stamps: np.ndarray) -> None:
    """`name`/000001.png ... and `name`.txt (RADIATE's `Frame: 000001 Time: s.nnnnnnnnn` lines)."""
    image_dir = out_dir / name
    image_dir.mkdir(parents=True, exist_ok=True)
    lines = []
    for index, (image, stamp) in enumerate(zip(scans, stamps), start=1):
        path = image_dir / f"{index:06d}.png"
        if not cv2.imwrite(str(path), image):
            raise OSError(f"could not write {path}")
        lines.append(f"Frame: {index:06d} Time: {format_timestamp(stamp)}\n")
    (out_dir / f"{name}.txt").write_text("".join(lines))


def write_sequence(sequence: SimulatedSequence, out_dir: Path, poses: bool = True, polar: bool = False) -> Path:
    """Create `out_dir` (a sequence folder) with Navtech_Cartesian/, its .txt, annotations, meta.json and (unless
    `poses` is False, like a real RADIATE sequence before `rafd-odometry`) ego_poses.csv with the true poses;
    polar=True adds Navtech_Polar/ + Navtech_Polar.txt (the same scans, uint8 [576 range bins, 400 azimuths])."""
    out_dir = Path(out_dir)
    if polar and (sequence.polar_scans is None or len(sequence.polar_scans) != len(sequence.images)):
        raise ValueError(f"sequence {sequence.name} carries no polar scan per frame; cannot write Navtech_Polar")
    _write_scans(out_dir, "Navtech_Cartesian", sequence.images, sequence.timestamps_ns)
    if polar and sequence.polar_scans is not None:  # (polar without scans raised above)
        _write_scans(out_dir, "Navtech_Polar", sequence.polar_scans, sequence.timestamps_ns)
    (out_dir / "annotations").mkdir(exist_ok=True)
    (out_dir / "annotations" / "annotations.json").write_text(json.dumps(annotations_json(sequence)))
    (out_dir / VELOCITIES_FILE).write_text(json.dumps(velocities_json(sequence)))
    meta = {
        "name": sequence.name,
        "type": "simulated",
        "set": sequence.split,
        "version": "1.0",
        "seed": int(sequence.seed),
        "resolution": sequence.resolution,
        "image_size": int(sequence.images[0].shape[0]),
        "weather": None if sequence.conditions is None else sequence.conditions.weather,  # like RADIATE's fog_*, rain_*
    }
    (out_dir / "meta.json").write_text(json.dumps(meta))
    if poses:
        _write_poses(out_dir / "ego_poses.csv", sequence)
    return out_dir
