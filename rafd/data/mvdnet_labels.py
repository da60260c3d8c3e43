"""MVDNet's published car labels of the Oxford Radar RobotCar (`label_2d/<UNIX microseconds>.txt` in a native folder,
rafd.data.native_folder), read as this project's boxes and as a sequence's objects (when the folder has no
annotations.json).

One car per line: `Car <track id> xc yc width length yaw_deg`, metres around the radar, drawn on the scan converted
with the Oxford SDK's convention: xc points right and yc backwards (image down), and yaw is the box's angle in the
image (clockwise on screen), so in this project's box convention (x, y, width, length, yaw) = (xc, -yc, width,
length, -radians(yaw_deg)). Established on the one labelled frame of `oxford_labelled`: the centres sit on (or
beside, on the far side: lidar labels box the whole car) the cars' returns, and the boxes' long sides lie along the
returns' elongation (its 3D labels, KITTI-style with z forward, give the same centres with z = -yc).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rafd.data.frames import RadarObject
from rafd.data.native_folder import text_microseconds
from rafd.geometry import box_polygons_pixels

MVDNET_LABELS = "label_2d"


def read_mvdnet_labels(path: Path) -> list[tuple[int, str, np.ndarray]]:
    """One MVDNet label_2d file -> [(track id, class name in lower case, box [5] in this project's convention)]."""
    out = []
    for number, line in enumerate(path.read_text().splitlines(), 1):
        fields = line.split()
        if not fields:
            continue
        if len(fields) != 7:
            raise ValueError(f"{path}:{number}: expected 'Car <track id> xc yc width length yaw_deg', got {line!r}")
        try:
            track = int(fields[1])
            xc, yc, width, length, yaw_deg = (float(v) for v in fields[2:])
        except ValueError as error:
            raise ValueError(f"{path}:{number}: {error}") from error
        out.append((track, fields[0].lower(), np.array([xc, -yc, width, length, -np.radians(yaw_deg)])))
    return out


def mvdnet_labels_by_scan(folder: Path, timestamps_us: list[int]) -> dict[int, list[tuple[int, str, np.ndarray]]]:
    """{scan timestamp: labels} from a native folder's label_2d/ (files named <timestamp>.txt or
    <timestamp>_label_2d.txt); scans without a file get none."""
    labels = folder / MVDNET_LABELS
    out: dict[int, list[tuple[int, str, np.ndarray]]] = {}
    for stamp in timestamps_us:
        for name in (f"{stamp}.txt", f"{stamp}_label_2d.txt"):
            if (labels / name).is_file():
                out[stamp] = read_mvdnet_labels(labels / name)
                break
    return out


def mvdnet_objects(
    folder: Path, numbers: list[int], texts: list[str], image_size: int, resolution: float
) -> dict[int, list[RadarObject]]:
    """A native folder's MVDNet labels as objects of its frames (frame numbers and canonical timestamp texts)."""
    stamps = [text_microseconds(text) for text in texts]
    by_scan = mvdnet_labels_by_scan(folder, stamps)
    objects: dict[int, list[RadarObject]] = {n: [] for n in numbers}
    for number, stamp in zip(numbers, stamps):
        for track, class_name, box in by_scan.get(stamp, []):
            polygon = box_polygons_pixels(box[None], image_size, resolution)[0]
            objects[number].append(RadarObject(track, class_name, polygon, box))
    return objects
