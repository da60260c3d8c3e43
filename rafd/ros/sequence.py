"""A bag as a sequence (rafd.data.reader.read_sequence reads one through here): its scan topic's messages are the
frames, numbered 1..N in log-time order, each frame's time its header stamp, its scan read from the bag when loaded
(BagScanSource) and converted to RADIATE's Cartesian grid like a native folder's. A bag carries no labels; its poses
come from `<bag>.ego_poses.csv` beside it (`rafd odometry BAG` writes it) when there is one, else from radar
odometry when asked for.

A bag is a rosbag2 folder (holding metadata.yaml) or a .mcap, .db3 or ROS 1 .bag file (is_bag).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rafd.geometry import RADIATE_RESOLUTION, RADIATE_SCAN_SIZE
from rafd.ros.reader import BagError, BagTopic, list_stamps, read_scans, scan_topic
from rafd.ros.scans import BagScan, RadarGeometry
from rafd.scans.native import NativeScan, format_for, native_format_name, parse_native_scan, to_cartesian
from rafd.scans.polar import polar_to_cartesian

log = logging.getLogger(__name__)

BAG_SUFFIXES = (".mcap", ".db3", ".bag")
POSES_SUFFIX = ".ego_poses.csv"


def is_bag(path: str | Path) -> bool:
    """Whether `path` is a bag: a rosbag2 folder (metadata.yaml in it) or a .mcap / .db3 / ROS 1 .bag file."""
    path = Path(path)
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    return path.is_file() and path.suffix in BAG_SUFFIXES


def poses_file(bag: str | Path) -> Path:
    """Where a bag's ego poses are kept: `<bag>.ego_poses.csv` beside it (a bag is not a folder rafd writes into)."""
    bag = Path(bag)
    return bag.with_name(bag.name + POSES_SUFFIX)


def native_scan_of(scan: BagScan) -> NativeScan:
    """A bag's native scan decoded as the service decodes it: named by its width and column 10, with the bag's
    range bin when it gives one."""
    pixels = scan.pixels
    first_us = int(np.ascontiguousarray(pixels[0, :8]).view("<i8")[0])
    fmt = format_for(native_format_name(pixels.shape[1], pixels[:, 10]), first_us).with_range_bin(scan.range_bin_m)
    return parse_native_scan(pixels, fmt)


def cartesian_of(scan: BagScan, size: int = RADIATE_SCAN_SIZE, resolution: float = RADIATE_RESOLUTION) -> np.ndarray:
    """A bag's scan -> uint8 [size, size] on RADIATE's grid (the conversion the service makes of it)."""
    if scan.layout == "polar":
        return polar_to_cartesian(scan.pixels, size, resolution)
    return to_cartesian(native_scan_of(scan), size, resolution)


@dataclass(frozen=True)
class BagScanSource:
    """One frame's scan in a bag: the message logged at `log_time_ns` on the topic, stamped `stamp_ns`."""

    topic: BagTopic
    log_time_ns: int
    stamp_ns: int
    size: int = RADIATE_SCAN_SIZE
    resolution: float = RADIATE_RESOLUTION

    def read(self) -> BagScan:
        """The scan message, decoded (BagError naming it when it is gone or does not read)."""
        for _, scan in read_scans(self.topic, self.log_time_ns, self.log_time_ns + 1):
            if scan.stamp_ns == self.stamp_ns:
                return scan
        raise BagError(f"{self.topic.path}: topic {self.topic.topic}: no scan stamped {self.stamp_ns} ns any more")

    def load(self, path: Path | None = None) -> np.ndarray:
        """uint8 [size, size] Cartesian scan (`path`, the bag, is the topic's: the frames' load protocol)."""
        return cartesian_of(self.read(), self.size, self.resolution)


def bag_frames(
    path: str | Path, topic: str | None = None, flags: RadarGeometry | None = None
) -> tuple[BagTopic, list[tuple[int, int]]]:
    """The bag's scan topic (named, or found by type; `flags`: the geometry where the bag has no configuration) and
    (log time, stamp) of its scans in log-time order; BagError when stamps do not increase (a stream's must)."""
    found = scan_topic(path, topic, flags)
    listed = list_stamps(found)
    stamps = [stamp for _, stamp in listed]
    for k in range(1, len(stamps)):
        if stamps[k] <= stamps[k - 1]:
            raise BagError(
                f"{found.path}: topic {found.topic}, message {k}: stamped {stamps[k]} ns, not after the previous "
                f"message's {stamps[k - 1]} ns (scans must be in time order)"
            )
    return found, listed
