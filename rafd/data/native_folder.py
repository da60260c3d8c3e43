"""Sequence folders of the datasets that store Navtech scans in the sensor's own polar layout (rafd.scans.native):
Oxford Radar RobotCar and Boreas.

Layout (Oxford's; Boreas keeps its scans the same way):
    radar/<UNIX microseconds>.png       one native scan per file, named after its first azimuth's time
    radar.timestamps                    optional: `<UNIX microseconds> <valid 0/1>` per scan (Oxford's index; without
                                        it the file names are the index)
    gt/radar_odometry.csv               optional (Oxford): the dataset's ground-truth radar odometry, used as the poses
    annotations/annotations.json        optional: labels in RADIATE's format keyed by scan timestamps (rafd.data.labels)
    label_2d/<UNIX microseconds>.txt    optional, when there is no annotations.json: MVDNet's published car labels
                                        (rafd.data.mvdnet_labels)
    meta.json                           optional: {"name", "set", "native_format" ("oxford", "boreas", "boreas-rt",
                                        ...); without it the first scan names the format as a posted scan's does:
                                        rafd.scans.native.native_format_name)

Scans are numbered 1..N in time order and converted on load to RADIATE's Cartesian grid (rafd.scans.native.NativeSource;
rafd.data.folders lists them), so everything downstream (datasets, evaluation, the client) reads them like a RADIATE
sequence.

Ground-truth odometry (Oxford's `radar_odometry.csv`: one row per consecutive pair, `source_radar_timestamp` the
newer scan, `destination_radar_timestamp` the older, x, y, yaw the newer scan's pose in the older one's frame, in the
dataset's axes: x forward, y right, yaw clockwise seen from above, i.e. z down). In this project's ego frame (x right, y
forward, yaw counter-clockwise) that is (x, y, yaw)_ours = (y, x, -yaw)_oxford: under it, radar odometry on the
converted scans agrees with the ground truth in sign and size on every pair of the real sample.
"""

from __future__ import annotations

import csv
import re
from pathlib import Path

import cv2
import numpy as np

from rafd.geometry import compose_poses
from rafd.scans.cartesian import load_image
from rafd.scans.native import FLAG_COLUMN, NativeFormat, format_for, is_native_shape, native_format_name

NATIVE_DIR = "radar"
NATIVE_TIMESTAMPS_FILE = "radar.timestamps"
GROUND_TRUTH_ODOMETRY = "gt/radar_odometry.csv"
_NATIVE_NAME = re.compile(r"(\d{13,19})\.png")


def is_native_folder(folder: Path) -> bool:
    """True when a folder holds native scans: radar/<microseconds>.png (Oxford, Boreas)."""
    radar = folder / NATIVE_DIR
    return radar.is_dir() and any(_NATIVE_NAME.fullmatch(p.name) for p in radar.iterdir())


def microseconds_text(microseconds: int) -> str:
    """UNIX microseconds -> the canonical 'seconds.nnnnnnnnn' text (rafd.data.radiate_files.parse_radiate_time's;
    nanoseconds, exact)."""
    return f"{microseconds // 1_000_000}.{(microseconds % 1_000_000) * 1000:09d}"


def text_microseconds(text: str) -> int:
    """A canonical 'seconds.nnnnnnnnn' text -> UNIX microseconds (microseconds_text's inverse: a native scan's name)."""
    return int(text.replace(".", "")) // 1000


def list_native_scans(folder: Path) -> list[tuple[int, Path]]:
    """[(UNIX microseconds, path)] of a native folder's scans in time order, checked against radar.timestamps when it
    is there (both ways); FileNotFoundError / ValueError naming the file otherwise."""
    radar = folder / NATIVE_DIR
    on_disk = {int(m.group(1)): p for p in radar.iterdir() if (m := _NATIVE_NAME.fullmatch(p.name))}
    if not on_disk:
        raise FileNotFoundError(f"{radar}: no native scans (<UNIX microseconds>.png)")
    index = folder / NATIVE_TIMESTAMPS_FILE
    if index.is_file():
        listed = []
        for number, line in enumerate(index.read_text().splitlines(), 1):
            fields = line.split()
            if not fields:
                continue
            if not fields[0].isdigit():
                raise ValueError(f"{index}:{number}: expected '<UNIX microseconds> <valid>', got {line!r}")
            listed.append(int(fields[0]))
        missing = [t for t in listed if t not in on_disk]
        if missing:
            raise FileNotFoundError(f"{index} lists {len(missing)} scans not in {radar} (first: {missing[0]}.png)")
        extra = sorted(set(on_disk) - set(listed))
        if extra:
            raise ValueError(f"{index} disagrees with the scans: {len(extra)} not listed (first: {extra[0]}.png)")
        if listed != sorted(listed) or len(set(listed)) != len(listed):
            raise ValueError(f"{index}: timestamps must increase")
    return sorted(on_disk.items())


def check_native_png(path: Path, width: int, height: int) -> None:
    if not is_native_shape(width, height):
        raise ValueError(
            f"{path} is {width}x{height} px; a native scan has one row per azimuth (some hundreds) and "
            "11 header columns + the range bins"
        )


def native_format_of(meta: dict[str, object], first_timestamp_us: int, first_scan: Path | None = None) -> NativeFormat:
    """meta.json's native_format; without it, what the first scan's width and column 10 say (native_format_name),
    or "oxford" when no scan is given."""
    if "native_format" not in meta and first_scan is not None:
        image = load_image(first_scan, cv2.IMREAD_UNCHANGED, "native radar scan")
        return format_for(native_format_name(image.shape[1], image[:, FLAG_COLUMN]), first_timestamp_us)
    name = meta.get("native_format", "oxford")
    if not isinstance(name, str):
        raise ValueError(f"meta.json native_format must be a string, got {name!r}")
    return format_for(name, first_timestamp_us)


def read_ground_truth_odometry(path: Path, timestamps_us: list[int]) -> np.ndarray:
    """Oxford's gt/radar_odometry.csv -> [N, 3] world poses (x, y, yaw in this project's axes) of the scans at
    `timestamps_us` (in time order), the first at (0, 0, 0), chained through every row between them (the file
    holds the rows of scans not on disk too). ValueError when the chain does not reach a scan."""
    step: dict[int, tuple[int, np.ndarray]] = {}  # older scan -> (newer scan, newer pose in the older frame)
    with path.open(newline="") as handle:
        for row in csv.DictReader(handle):
            try:
                newer, older = int(row["source_radar_timestamp"]), int(row["destination_radar_timestamp"])
                x, y, yaw = float(row["x"]), float(row["y"]), float(row["yaw"])
            except (KeyError, ValueError) as error:
                raise ValueError(f"{path}: not Oxford's radar_odometry.csv ({error})") from error
            step[older] = (newer, np.array([y, x, -yaw]))  # dataset axes (x fwd, y right, z down) -> ours
    poses = [np.zeros(3)]
    current, pose = timestamps_us[0], np.zeros(3)
    for target in timestamps_us[1:]:
        while current != target:
            if current not in step or current > target:
                raise ValueError(f"{path}: the odometry rows do not lead from scan {timestamps_us[0]} to {target}")
            current, relative = step[current]
            pose = compose_poses(pose, relative)
        poses.append(pose)
    return np.stack(poses)
