"""RADIATE's per-sequence files, parsed and checked: the scans' timestamp file (Navtech_Cartesian.txt or
Navtech_Polar.txt), meta.json and annotations/annotations.json (which file lies where: rafd.data.folders).

    Navtech_Cartesian.txt              `Frame: 000001 Time: 1574859771.744660272`, one line per scan
    annotations/annotations.json      [{"id", "class_name", "bboxes"}], bboxes[k] = frame k + 1 ([] if absent)
    meta.json                          {"name", "set" (the split), ...; simulated: "image_size", "resolution";
                                       labelled scans: "labelled_half_m", the labelled square, ignored outside}

Rules: times are read as the RADIATE SDK reads them (parse_radiate_time); annotations are indexed by frame number
(the list can be longer than the frames on disk); polygons follow the RADIATE SDK (corners of [x0, y0, w, h] rotated
about the centre by R(deg2rad(-rotation)) in pixels); boxes are metres in the ego frame via geometry.radiate_to_box
with the image's own size. Bad data raises FileNotFoundError/ValueError naming the file; anything skipped is counted
in a log warning.
"""

from __future__ import annotations

import json
import logging
import math
import re
from collections.abc import Mapping
from pathlib import Path

from rafd.data.frames import RadarObject
from rafd.data.labels import IGNORE_CLASS, index_by_frame, timestamp_keyed
from rafd.geometry import radiate_polygon, radiate_to_box

log = logging.getLogger(__name__)

RADIATE_CLASSES = ("car", "van", "truck", "bus", "motorbike", "bicycle", "pedestrian", "group_of_pedestrians")
_TIMESTAMP_LINE = re.compile(r"Frame:\s*(\d+)\s+Time:\s*([0-9]+(?:\.[0-9]+)?)\s*")
NANOSECOND_DIGITS = 9


def parse_radiate_time(text: str) -> tuple[float, str]:
    """A RADIATE `Time:` field -> (UNIX seconds, canonical 'seconds.nnnnnnnnn' text), as the RADIATE SDK reads it.

    The recording software printed the nanosecond field without zero padding, so a fraction of fewer than 9 digits
    is nanoseconds, not a decimal fraction: '1574859771.74466027' is 1574859771 s + 74466027 ns = ...771.074466027
    (the SDK's "fixing timestamp problem" change left-pads it with zeros). 9 digits read as they are.
    """
    seconds, dot, fraction = text.strip().partition(".")
    if not seconds.isdigit() or (dot and not fraction.isdigit()):
        raise ValueError(f"not a RADIATE timestamp: {text!r}")
    if len(fraction) > NANOSECOND_DIGITS:
        raise ValueError(f"timestamp {text!r} has more than {NANOSECOND_DIGITS} fractional (nanosecond) digits")
    canonical = f"{int(seconds)}.{fraction.zfill(NANOSECOND_DIGITS)}"
    return float(canonical), canonical


def read_timestamps(path: Path) -> list[tuple[int, float, str]]:
    """Navtech_Cartesian.txt (or Navtech_Polar.txt) -> [(frame number, UNIX seconds, canonical 9-digit text)] in
    file order, validated.

    Times are read as the RADIATE SDK reads them (parse_radiate_time: a short fraction is zero-padded nanoseconds).
    """
    if not path.is_file():
        raise FileNotFoundError(f"timestamp file {path} not found (not a RADIATE sequence folder?)")
    entries: list[tuple[int, float, str]] = []
    for line_number, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        match = _TIMESTAMP_LINE.fullmatch(line.strip())
        if match is None:
            raise ValueError(f"{path}:{line_number}: expected 'Frame: 000001 Time: 1574859771.744660272', got {line!r}")
        number = int(match.group(1))
        try:
            stamp, text = parse_radiate_time(match.group(2))
        except ValueError as error:
            raise ValueError(f"{path}:{line_number}: {error}") from error
        if entries and number <= entries[-1][0]:
            raise ValueError(f"{path}:{line_number}: frame {number} after frame {entries[-1][0]}; frames must increase")
        if entries and stamp <= entries[-1][1]:
            raise ValueError(f"{path}:{line_number}: time {stamp} does not increase (previous {entries[-1][1]})")
        entries.append((number, stamp, text))
    if not entries:
        raise ValueError(f"{path}: no frames listed")
    return entries


def read_meta(path: Path) -> dict:
    """meta.json -> dict ({} with a warning when missing)."""
    if not path.is_file():
        log.warning("%s not found: split unknown (None), name from the folder", path)
        return {}
    meta = _read_json(path)
    if not isinstance(meta, dict):
        raise ValueError(f"{path}: expected a JSON object, got {type(meta).__name__}")
    if "set" in meta and not isinstance(meta["set"], str):
        raise ValueError(f"{path}: 'set' must be a string, got {meta['set']!r}")
    return meta


def meta_condition(meta: dict) -> str | None:
    """meta.json -> the recording condition: the simulator's "weather" (clear, fog, rain), else RADIATE's "type"
    (e.g. "fog" for fog_6_0); None when neither names one."""
    for key in ("weather", "type"):
        value = meta.get(key)
        if isinstance(value, str) and value and value != "simulated":
            return value
    return None


def _read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise ValueError(f"{path}: malformed JSON ({error})") from error
    except (OSError, UnicodeDecodeError) as error:
        raise ValueError(f"{path}: cannot read ({error})") from error


def finite_number(value, path: Path, where: str) -> float:
    """A JSON value that must be a finite number (not a bool) -> float; ValueError naming the file and the place."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise ValueError(f"{path}: {where}: expected a finite number, got {value!r}")
    return float(value)


def read_annotations(
    path: Path,
    frame_numbers: list[int],
    image_size: int,
    resolution: float,
    frames_by_timestamp: Mapping[int, int] | None = None,
) -> dict[int, list[RadarObject]]:
    """annotations.json -> {frame number: objects} for the frames on disk (bboxes[k] is frame k + 1). A label file
    keyed by scan timestamps (rafd.data.labels, native folders) is read through `frames_by_timestamp`."""
    entries = _read_json(path)
    if timestamp_keyed(entries):
        if frames_by_timestamp is None:
            raise ValueError(f"{path}: keys its boxes by scan timestamps; only a native folder's scans have them")
        try:
            entries = index_by_frame(entries, frames_by_timestamp)
        except ValueError as error:
            raise ValueError(f"{path}: {error}") from error
    if not isinstance(entries, list):
        raise ValueError(f"{path}: expected a JSON list of objects, got {type(entries).__name__}")
    objects: dict[int, list[RadarObject]] = {n: [] for n in frame_numbers}
    skipped_size, unknown_classes, duplicates = 0, set(), 0
    for index, entry in enumerate(entries):
        if not isinstance(entry, dict) or not {"id", "class_name", "bboxes"} <= set(entry):
            raise ValueError(f"{path}: entry {index} must be an object with 'id', 'class_name' and 'bboxes'")
        object_id, class_name, bboxes = entry["id"], entry["class_name"], entry["bboxes"]
        if isinstance(object_id, bool) or not isinstance(object_id, int):
            raise ValueError(f"{path}: entry {index}: 'id' must be an integer, got {object_id!r}")
        if not isinstance(class_name, str) or not class_name:
            raise ValueError(f"{path}: entry {index} (id {object_id}): 'class_name' must be a non-empty string")
        if not isinstance(bboxes, list):
            raise ValueError(f"{path}: entry {index} (id {object_id}): 'bboxes' must be a list")
        if class_name not in RADIATE_CLASSES and class_name != IGNORE_CLASS:
            unknown_classes.add(class_name)
        for number in frame_numbers:
            if number < 1 or number > len(bboxes):
                continue  # not annotated beyond the list: absent
            annotation = bboxes[number - 1]
            if annotation in ([], {}, None):
                continue
            where = f"entry {index} (id {object_id}), frame {number}"
            if not isinstance(annotation, dict) or "position" not in annotation or "rotation" not in annotation:
                raise ValueError(f"{path}: {where}: expected [] or {{'position': [x, y, w, h], 'rotation': deg}}")
            position = annotation["position"]
            if not isinstance(position, list) or len(position) != 4:
                raise ValueError(f"{path}: {where}: 'position' must be [x, y, w, h], got {position!r}")
            position = [finite_number(v, path, where) for v in position]
            rotation = finite_number(annotation["rotation"], path, where)
            if position[2] <= 0 or position[3] <= 0:
                skipped_size += 1
                continue
            if any(o.id == object_id for o in objects[number]):
                duplicates += 1
            objects[number].append(
                RadarObject(
                    id=object_id,
                    class_name=class_name,
                    polygon=radiate_polygon(position, rotation),
                    box=radiate_to_box(position, rotation, image_size=image_size, resolution=resolution),
                )
            )
    if skipped_size:
        log.warning("%s: skipped %d annotations with zero or negative width/height", path, skipped_size)
    if unknown_classes:
        log.warning("%s: class names outside RADIATE's %s: %s", path, RADIATE_CLASSES, sorted(unknown_classes))
    if duplicates:
        log.warning("%s: %d annotations repeat an id already used in the same frame", path, duplicates)
    return objects
