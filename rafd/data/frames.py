"""What a sequence folder is read into (rafd.data.reader.read_sequence): a RadarSequence of RadarFrames, each with
its RadarObjects (the labels, boxes in metres in the frame's ego frame) and the scan it loads as a Cartesian one.

A frame of a polar-only or native folder keeps its scan file as it is on disk and converts it on load (its `polar`
source: rafd.scans.polar.PolarSource, rafd.scans.native.NativeSource); a frame of a ROS 2 bag reads its message from
the bag (image_path) on load (rafd.ros.sequence.BagScanSource).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from rafd.geometry import RADIATE_RESOLUTION
from rafd.scans.cartesian import load_image
from rafd.scans.native import NativeSource
from rafd.scans.polar import PolarSource

if TYPE_CHECKING:
    from rafd.ros.sequence import BagScanSource


@dataclass(frozen=True, eq=False)
class RadarObject:
    id: int
    class_name: str  # RADIATE's class name, as annotated
    polygon: np.ndarray  # [4, 2] corner pixels (u, v) of the full scan, RADIATE SDK order
    box: np.ndarray  # [5] (x, y, width, length, yaw) metres / radians in this frame's ego frame


@dataclass(frozen=True, eq=False)
class RadarFrame:
    number: int  # RADIATE frame number (the N of 00000N.png)
    timestamp: float  # UNIX seconds
    image_path: Path  # the Cartesian scan, or the polar scan when `polar` is set
    objects: list[RadarObject] = field(default_factory=list)
    # set for polar-only and native folders and bags: load() converts
    polar: PolarSource | NativeSource | BagScanSource | None = None
    timestamp_text: str = ""  # canonical 'seconds.nnnnnnnnn' (parse_radiate_time): the exact time, all 9 digits

    @property
    def timestamp_ns(self) -> int:
        """UNIX nanoseconds, exact when timestamp_text is known (a float64 keeps only ~0.2 us at today's dates)."""
        if not self.timestamp_text:
            return round(self.timestamp * 1e9)
        seconds, fraction = self.timestamp_text.split(".")
        return int(seconds) * 1_000_000_000 + int(fraction)

    def load(self) -> np.ndarray:
        """uint8 [H, W] Cartesian scan."""
        return load_image(self.image_path) if self.polar is None else self.polar.load(self.image_path)


@dataclass(frozen=True, eq=False)
class RadarSequence:
    name: str
    split: str | None  # meta.json "set"; None without meta.json
    path: Path
    frames: list[RadarFrame]
    # [N, 3] world poses (x, y, yaw), row k = frames[k]; None when neither a file nor odometry gave them.
    # (The contract said dict frame -> pose; the consumers index by position: see pose_of for numbers.)
    poses: np.ndarray | None
    pose_source: str | None  # "file" (ego_poses.csv), "odometry" (estimated here) or None
    image_size: int = 0  # pixels per side of every scan
    resolution: float = RADIATE_RESOLUTION  # metres per pixel
    annotated: bool = True  # False when the folder has no annotations/annotations.json
    # Recording condition from meta.json: the simulator's "weather", else RADIATE's "type" (e.g. "fog").
    condition: str | None = None

    def __len__(self) -> int:
        return len(self.frames)

    def load_image(self, index: int) -> np.ndarray:
        """uint8 [H, W] scan of frames[index] (a position in `frames`, not a frame number)."""
        return self.frames[index].load()

    def frame_index(self, number: int) -> int:
        """Position in `frames` of RADIATE frame `number` (KeyError if absent)."""
        for index, frame in enumerate(self.frames):
            if frame.number == number:
                return index
        raise KeyError(f"{self.path}: no frame {number}")

    def pose_of(self, number: int) -> np.ndarray:
        """[3] world pose of RADIATE frame `number`."""
        if self.poses is None:
            raise ValueError(f"{self.path}: sequence has no poses")
        return self.poses[self.frame_index(number)]

    def poses_by_frame(self) -> dict[int, np.ndarray]:
        """{frame number: [3] world pose} (the contract's mapping form); {} without poses."""
        if self.poses is None:
            return {}
        return {frame.number: pose for frame, pose in zip(self.frames, self.poses)}
