"""Labels of scans named by their timestamps (native Oxford / Boreas folders): RADIATE's annotation format, each
track's boxes keyed by the scan's UNIX-microsecond timestamp instead of its frame index, so a label file stays valid
whatever subset of a recording's scans a folder holds.

    [{"id": 1, "class_name": "car",
      "bboxes": {"1547131046353776": {"position": [x0, y0, w, h], "rotation": deg}, ...}}, ...]

`position` / `rotation` are RADIATE's (pixels of the 1152 px scan at 0.173611 m/px, radar at the centre; the box
rotated about its centre by R(deg2rad(-rotation)) in pixel coordinates; rafd.geometry.radiate_to_box gives metres).
A track of class IGNORE_CLASS marks a region where the labeller could not decide: it neither rewards nor penalises
(evaluation drops detections whose centre falls inside it, training does not push the heatmap down inside it).

Boxes are entered by a person as text (`rafd-label apply`, one box per line, metres in the ego frame):
    <timestamp us> <track id> <class> <x m> <y m> <width m> <length m> <yaw deg>
x right, y forward, yaw counter-clockwise from the x axis (rafd.geometry's box convention).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rafd.geometry import RADIATE_RESOLUTION, RADIATE_SCAN_SIZE, box_to_radiate

IGNORE_CLASS = "ignore"
LABEL_CLASSES = ("car", "van", "truck", "bus", "motorbike", "bicycle", IGNORE_CLASS)
# meta.json key: half the side of the square around the radar in which every vehicle is labelled (the protocol's
# 30 m, docs/labelling.md); outside it the sequence's frames carry ignore regions (outside_square).
LABELLED_AREA_KEY = "labelled_half_m"


@dataclass(frozen=True)
class LabelBox:
    """One box of one scan: metres and radians in that scan's ego frame."""

    timestamp_us: int
    track: int
    class_name: str
    box: np.ndarray  # [5] (x, y, width, length, yaw)


def parse_box_lines(lines: Iterable[str], where: str = "labels") -> list[LabelBox]:
    """The text a labeller writes (module docstring) -> boxes; '#' starts a comment. ValueError naming the line."""
    boxes = []
    for number, raw in enumerate(lines, 1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        fields = line.split()
        if len(fields) != 8:
            raise ValueError(
                f"{where}:{number}: expected 8 fields (timestamp track class x y width length yaw_deg), "
                f"got {len(fields)}: {raw.strip()!r}"
            )
        try:
            stamp, track = int(fields[0]), int(fields[1])
            x, y, width, length, yaw_deg = (float(v) for v in fields[3:])
        except ValueError as error:
            raise ValueError(f"{where}:{number}: {error}") from error
        if fields[2] not in LABEL_CLASSES:
            raise ValueError(f"{where}:{number}: class {fields[2]!r} is not one of {LABEL_CLASSES}")
        if not all(math.isfinite(v) for v in (x, y, width, length, yaw_deg)) or width <= 0 or length <= 0:
            raise ValueError(f"{where}:{number}: sizes must be positive and every number finite")
        boxes.append(LabelBox(stamp, track, fields[2], np.array([x, y, width, length, math.radians(yaw_deg)])))
    return boxes


def to_annotations(
    boxes: Iterable[LabelBox], image_size: int = RADIATE_SCAN_SIZE, resolution: float = RADIATE_RESOLUTION
) -> list[dict[str, object]]:
    """Boxes -> the label file's JSON (tracks sorted by id, boxes by timestamp). ValueError when a track changes
    class or holds two boxes in one scan."""
    tracks: dict[int, dict[str, object]] = {}
    for label in sorted(boxes, key=lambda b: (b.track, b.timestamp_us)):
        track = tracks.setdefault(label.track, {"id": label.track, "class_name": label.class_name, "bboxes": {}})
        if track["class_name"] != label.class_name:
            raise ValueError(f"track {label.track} is both {track['class_name']} and {label.class_name}")
        bboxes = track["bboxes"]
        assert isinstance(bboxes, dict)
        key = str(label.timestamp_us)
        if key in bboxes:
            raise ValueError(f"track {label.track} has two boxes in scan {key}")
        position, rotation = box_to_radiate(label.box, image_size, resolution)
        bboxes[key] = {"position": [round(p, 3) for p in position], "rotation": round(rotation, 3)}
    return list(tracks.values())


def write_annotations(path: Path, annotations: list[dict[str, object]]) -> Path:
    """The label file, written atomically (one track per line, for readable diffs)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    text = "[\n" + ",\n".join(json.dumps(track, sort_keys=True) for track in annotations) + "\n]\n"
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    tmp.replace(path)
    return path


def timestamp_keyed(entries: object) -> bool:
    """Whether a parsed annotations.json keys its boxes by scan timestamps (this module) rather than frame index."""
    return (
        isinstance(entries, list)
        and bool(entries)
        and isinstance(entries[0], dict)
        and isinstance(entries[0].get("bboxes"), dict)
    )


def index_by_frame(entries: list[dict[str, object]], frames_by_timestamp: Mapping[int, int]) -> list[dict[str, object]]:
    """Timestamp-keyed tracks -> RADIATE's frame-indexed form (bboxes[k] = frame k + 1) for the scans of a folder;
    boxes of scans the folder does not hold are dropped (a label file may cover more of the recording)."""
    count = max(frames_by_timestamp.values(), default=0)
    out = []
    for track in entries:
        bboxes = track.get("bboxes")
        if not isinstance(bboxes, dict):
            raise ValueError("a label file keys every track's boxes by timestamp, or none")
        indexed: list[object] = [[] for _ in range(count)]
        for key, box in bboxes.items():
            if not str(key).isdigit():
                raise ValueError(f"track {track.get('id')}: box key {key!r} is not a UNIX-microsecond timestamp")
            frame = frames_by_timestamp.get(int(key))
            if frame is not None:
                indexed[frame - 1] = box
        out.append({**track, "bboxes": indexed})
    return out


def outside_square(half_m: float, extent_m: float) -> np.ndarray:
    """[4, 5] boxes (x, y, width, length, yaw) covering everything outside the square |x|, |y| <= half_m, out to
    extent_m from the radar: where nobody labelled. As ignore regions they keep a training crop cut away from the
    radar (a tile shift, a rotation) from teaching that the unlabelled vehicles beyond the square are background,
    and keep evaluation from counting detections there as false positives."""
    if not 0.0 < half_m < extent_m:
        raise ValueError(f"the labelled half side must be in (0, {extent_m}) m, got {half_m}")
    depth, centre = extent_m - half_m, (extent_m + half_m) / 2.0
    return np.array(
        [
            [centre, 0.0, depth, 2.0 * extent_m, 0.0],  # right of the square, the whole height
            [-centre, 0.0, depth, 2.0 * extent_m, 0.0],  # left
            [0.0, centre, 2.0 * half_m, depth, 0.0],  # ahead, between the side strips
            [0.0, -centre, 2.0 * half_m, depth, 0.0],  # behind
        ]
    )
