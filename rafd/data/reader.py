"""Read one RADIATE sequence folder (real or simulated) into frames, objects and ego poses.

Folder layout (RADIATE's, docs/data.md):
    Navtech_Cartesian/000001.png ...   uint8 grey Cartesian scans, radar at the image centre
    Navtech_Cartesian.txt              `Frame: 000001 Time: 1574859771.744660272`, one line per scan
    Navtech_Polar/000001.png ...       or, instead of the two above, the sensor's polar scans uint8 [576, 400]
    Navtech_Polar.txt                  (+ their timestamps), converted to the Cartesian grid on load (rafd.polar)
    radar/<microseconds>.png ...       or the scans in the sensor's native layout (Oxford Radar RobotCar, Boreas;
                                       rafd.data.native_folder), converted on load (rafd.native)
    annotations/annotations.json      [{"id", "class_name", "bboxes"}], bboxes[k] = frame k + 1 ([] if absent)
    meta.json                          {"name", "set" (the split), ...; simulated: "image_size", "resolution";
                                       labelled scans: "labelled_half_m", the labelled square, ignored outside}
    ego_poses.csv                      optional, ours (rafd.data.poses): frame, timestamp, x, y, yaw

Rules: annotations are indexed by frame number (the list can be longer than the frames on disk);
polygons follow the RADIATE SDK (corners of [x0, y0, w, h] rotated about the centre by
R(deg2rad(-rotation)) in pixels); boxes are metres in the ego frame via geometry.radiate_to_box with the
image's own size. Bad data raises FileNotFoundError/ValueError naming the file; anything skipped is
counted in a log warning. Poses come from ego_poses.csv ("file"), else from radar odometry ("odometry",
logged), never silently identity. A folder with both Cartesian and polar scans (RADIATE ships both) is read
from its Cartesian scans; a polar-only folder gives scans of meta.json "image_size" pixels (default: the whole
polar disc, 1152 for RADIATE), and RadarFrame.load() / FrameList.load() convert each on load.
"""

from __future__ import annotations

import json
import logging
import math
import re
import struct
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from rafd.data.labels import IGNORE_CLASS, LABELLED_AREA_KEY, index_by_frame, outside_square, timestamp_keyed
from rafd.data.native_folder import (
    GROUND_TRUTH_ODOMETRY,
    MVDNET_LABELS,
    NativeSource,
    check_native_png,
    is_native_folder,
    list_native_scans,
    microseconds_text,
    mvdnet_labels_by_scan,
    native_format_of,
    read_ground_truth_odometry,
)
from rafd.data.poses import POSES_FILE, read_ego_poses
from rafd.geometry import RADIATE_RESOLUTION, RADIATE_SCAN_SIZE, box_polygons_pixels, radiate_polygon, radiate_to_box
from rafd.polar import RADIATE_POLAR, cartesian_size, polar_to_cartesian

log = logging.getLogger(__name__)

IMAGE_DIR = "Navtech_Cartesian"
TIMESTAMPS_FILE = "Navtech_Cartesian.txt"
POLAR_DIR = "Navtech_Polar"
POLAR_TIMESTAMPS_FILE = "Navtech_Polar.txt"
ANNOTATIONS_FILE = "annotations/annotations.json"
META_FILE = "meta.json"
RADIATE_CLASSES = ("car", "van", "truck", "bus", "motorbike", "bicycle", "pedestrian", "group_of_pedestrians")
POSE_TIMESTAMP_TOLERANCE = 1e-3  # seconds: ego_poses.csv rows must carry their frame's timestamp

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_TIMESTAMP_LINE = re.compile(r"Frame:\s*(\d+)\s+Time:\s*([0-9]+(?:\.[0-9]+)?)\s*")
NANOSECOND_DIGITS = 9
_IMAGE_NAME = re.compile(r"(\d+)\.png")


@dataclass(frozen=True, eq=False)
class RadarObject:
    id: int
    class_name: str  # RADIATE's class name, as annotated
    polygon: np.ndarray  # [4, 2] corner pixels (u, v) of the full scan, RADIATE SDK order
    box: np.ndarray  # [5] (x, y, width, length, yaw) metres / radians in this frame's ego frame


@dataclass(frozen=True)
class PolarSource:
    """How a polar-only folder's scans become Cartesian ones: the side and resolution of the converted scan."""

    size: int  # pixels per side
    resolution: float  # metres per pixel

    def load(self, path: Path) -> np.ndarray:
        """Navtech_Polar PNG -> uint8 [size, size] Cartesian scan (RADIATE's conventions)."""
        polar = load_image(path)
        try:
            return polar_to_cartesian(polar, self.size, self.resolution)
        except ValueError as error:
            raise ValueError(f"polar scan {path}: {error}") from error


@dataclass(frozen=True, eq=False)
class RadarFrame:
    number: int  # RADIATE frame number (the N of 00000N.png)
    timestamp: float  # UNIX seconds
    image_path: Path  # the Cartesian scan, or the polar scan when `polar` is set
    objects: list[RadarObject] = field(default_factory=list)
    polar: PolarSource | NativeSource | None = None  # set for polar-only and native folders: load() converts
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


# ---------------------------------------------------------------- images
def load_image(path: str | Path) -> np.ndarray:
    """uint8 [H, W] grey image; FileNotFoundError / ValueError naming the file when missing or undecodable."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"radar image {path} not found")
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise ValueError(f"radar image {path} is corrupt or not an image (cv2.imread failed)")
    return image


def png_size(path: Path) -> tuple[int, int]:
    """(width, height) from a PNG's IHDR header (24 bytes read); ValueError naming the file if not a PNG."""
    try:
        with path.open("rb") as handle:
            head = handle.read(24)
    except FileNotFoundError:
        raise FileNotFoundError(f"radar image {path} not found") from None
    except OSError as error:
        raise ValueError(f"radar image {path} cannot be read ({error})") from error
    if len(head) < 24 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
        raise ValueError(f"radar image {path} is corrupt or not a PNG (bad header)")
    width, height = struct.unpack(">II", head[16:24])
    return int(width), int(height)


# ---------------------------------------------------------------- files of a sequence
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


def _number(value, path: Path, where: str) -> float:
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
            position = [_number(v, path, where) for v in position]
            rotation = _number(annotation["rotation"], path, where)
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


def _check_images(
    folder: Path, numbers: list[int], timestamps_path: Path, image_dir_name: str = IMAGE_DIR
) -> tuple[list[Path], tuple[int, int]]:
    """Image path per listed frame, checked against the folder (both ways) and the PNG headers -> (paths, (width,
    height)). Cartesian scans must be square; polar scans ([range bins, azimuths]) need not."""
    image_dir = folder / image_dir_name
    if not image_dir.is_dir():
        raise FileNotFoundError(f"image folder {image_dir} not found (not a RADIATE sequence folder?)")
    on_disk: dict[int, Path] = {}
    ignored = 0
    for entry in image_dir.iterdir():
        match = _IMAGE_NAME.fullmatch(entry.name)
        if match:
            on_disk[int(match.group(1))] = entry
        else:
            ignored += 1
    if ignored:
        log.warning("%s: ignored %d files that are not NNNNNN.png scans", image_dir, ignored)
    paths = []
    for number in numbers:
        if number not in on_disk:
            raise FileNotFoundError(
                f"radar image {image_dir / f'{number:06d}.png'} not found ({timestamps_path.name} lists frame {number})"
            )
        paths.append(on_disk[number])
    extra = sorted(set(on_disk) - set(numbers))
    if extra:
        names = ", ".join(on_disk[n].name for n in extra[:5]) + (" ..." if len(extra) > 5 else "")
        raise ValueError(f"{timestamps_path} disagrees with the images: no timestamp for {len(extra)} scans ({names})")
    sizes: dict[tuple[int, int], Path] = {}
    for path in paths:
        width, height = png_size(path)
        if width != height and image_dir_name == IMAGE_DIR:
            raise ValueError(
                f"radar image {path} is {width}x{height}; scans must be square with the radar at the centre"
            )
        sizes.setdefault((width, height), path)
    if len(sizes) > 1:
        detail = ", ".join(f"{w}x{h} px ({path.name})" for (w, h), path in sizes.items())
        raise ValueError(f"{image_dir}: scans differ in size: {detail}")
    return paths, next(iter(sizes))


def _file_poses(path: Path, numbers: list[int], stamps: list[float]) -> np.ndarray:
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


@dataclass(frozen=True, eq=False)
class FrameList:
    """A sequence folder's scans without annotations or poses (validated like read_sequence)."""

    folder: Path
    numbers: list[int]
    timestamps: list[float]
    timestamp_texts: list[str]  # canonical 'seconds.nnnnnnnnn' texts (parse_radiate_time), all nanosecond digits
    image_paths: list[Path]  # Cartesian scans, or polar scans when `polar` is set
    image_size: int  # pixels per side of the (converted) Cartesian scans
    resolution: float
    meta: dict
    polar: PolarSource | NativeSource | None = None  # set for polar-only and native folders: load() converts

    def load(self, index: int) -> np.ndarray:
        """uint8 [S, S] Cartesian scan of image_paths[index] (converted from the polar scan in polar-only folders)."""
        path = self.image_paths[index]
        return load_image(path) if self.polar is None else self.polar.load(path)


def is_polar_only(folder: Path) -> bool:
    """True when a folder holds the polar scans (Navtech_Polar/ or its .txt) and no Cartesian ones."""
    cartesian = (folder / IMAGE_DIR).is_dir() or (folder / TIMESTAMPS_FILE).is_file()
    return not cartesian and ((folder / POLAR_DIR).is_dir() or (folder / POLAR_TIMESTAMPS_FILE).is_file())


def list_frames(path: str | Path) -> FrameList:
    """Frame numbers, timestamps and image paths of a sequence folder, checked against each other, and
    meta.json (split, optional image_size / resolution). Polar-only folders list their Navtech_Polar scans."""
    folder = Path(path)
    if not folder.is_dir():
        raise FileNotFoundError(
            f"sequence folder {folder} not found (expected {folder / TIMESTAMPS_FILE} and {folder / IMAGE_DIR}/, "
            f"or {POLAR_TIMESTAMPS_FILE} and {POLAR_DIR}/)"
        )
    if is_native_folder(folder):
        return _list_native_frames(folder)
    polar_only = is_polar_only(folder)
    timestamps_path = folder / (POLAR_TIMESTAMPS_FILE if polar_only else TIMESTAMPS_FILE)
    listed = read_timestamps(timestamps_path)
    numbers, stamps = [n for n, _, _ in listed], [t for _, t, _ in listed]
    image_dir = POLAR_DIR if polar_only else IMAGE_DIR
    image_paths, (width, height) = _check_images(folder, numbers, timestamps_path, image_dir)
    meta_path = folder / META_FILE
    meta = read_meta(meta_path)
    resolution = RADIATE_RESOLUTION
    if "resolution" in meta:
        resolution = _number(meta["resolution"], meta_path, "resolution")
        if resolution <= 0:
            raise ValueError(f"{meta_path}: resolution must be positive, got {resolution}")
    polar: PolarSource | None = None
    if polar_only:
        # PNG width x height = azimuths x range bins. meta.json's image_size (a simulated folder) names the
        # Cartesian scans the annotations were made on; RADIATE's polar disc fills 1152 px.
        image_size = cartesian_size(height, resolution, RADIATE_POLAR)
        if "image_size" in meta:
            image_size = meta["image_size"]
            if isinstance(image_size, bool) or not isinstance(image_size, int) or image_size < 2 or image_size % 2:
                raise ValueError(f"{meta_path}: image_size must be an even number of pixels, got {image_size!r}")
        polar = PolarSource(image_size, resolution)
        log.info(
            "%s: polar-only sequence (%d range bins x %d azimuths): scans are converted to %d px on load",
            folder,
            height,
            width,
            image_size,
        )
    else:
        image_size = width
        if "image_size" in meta and meta["image_size"] != image_size:
            raise ValueError(f"{meta_path}: image_size {meta['image_size']!r} but the scans are {image_size} px")
    return FrameList(
        folder, numbers, stamps, [text for _, _, text in listed], image_paths, image_size, resolution, meta, polar
    )


def _list_native_frames(folder: Path) -> FrameList:
    """A native folder (rafd.data.native_folder): scans numbered 1..N in time order, converted to RADIATE's grid."""
    scans = list_native_scans(folder)
    meta = read_meta(folder / META_FILE)
    for _, path in scans[:1]:
        check_native_png(path, *png_size(path))
    image_size = meta.get("image_size", RADIATE_SCAN_SIZE)
    if isinstance(image_size, bool) or not isinstance(image_size, int) or image_size < 2 or image_size % 2:
        raise ValueError(f"{folder / META_FILE}: image_size must be an even number of pixels, got {image_size!r}")
    source = NativeSource(native_format_of(meta, scans[0][0]), image_size, RADIATE_RESOLUTION)
    texts = [microseconds_text(us) for us, _ in scans]
    return FrameList(
        folder,
        list(range(1, len(scans) + 1)),
        [float(text) for text in texts],
        texts,
        [path for _, path in scans],
        image_size,
        RADIATE_RESOLUTION,
        meta,
        source,
    )


def _mvdnet_objects(
    folder: Path, numbers: list[int], texts: list[str], image_size: int, resolution: float
) -> dict[int, list[RadarObject]]:
    """A native folder's MVDNet labels (rafd.data.native_folder) as objects of its frames."""
    stamps = [int(text.replace(".", "")) // 1000 for text in texts]
    by_scan = mvdnet_labels_by_scan(folder, stamps)
    objects: dict[int, list[RadarObject]] = {n: [] for n in numbers}
    for number, stamp in zip(numbers, stamps):
        for track, class_name, box in by_scan.get(stamp, []):
            polygon = box_polygons_pixels(box[None], image_size, resolution)[0]
            objects[number].append(RadarObject(track, class_name, polygon, box))
    return objects


def _ignore_outside_labelled_area(
    objects: dict[int, list[RadarObject]], half_m: object, folder: Path, image_size: int, resolution: float
) -> None:
    """meta.json's labelled_half_m: every frame gains ignore regions over the scan outside the labelled square."""
    if isinstance(half_m, bool) or not isinstance(half_m, (int, float)):
        raise ValueError(f"{folder / META_FILE}: {LABELLED_AREA_KEY} must be a number of metres, got {half_m!r}")
    boxes = outside_square(float(half_m), image_size * resolution)  # the scan's half diagonal is less
    polygons = box_polygons_pixels(boxes, image_size, resolution)
    for frame_objects in objects.values():
        frame_objects += [RadarObject(-1 - k, IGNORE_CLASS, polygons[k], boxes[k]) for k in range(len(boxes))]


def read_sequence(path: str | Path, estimate_poses: bool = True) -> RadarSequence:
    """One RADIATE sequence folder -> RadarSequence. estimate_poses=False skips odometry when the folder has no
    ego_poses.csv (poses None, pose_source None): for tools that only need frames and annotations."""
    listing = list_frames(path)
    folder, numbers, stamps = listing.folder, listing.numbers, listing.timestamps
    image_size, resolution, meta = listing.image_size, listing.resolution, listing.meta

    annotations_path = folder / ANNOTATIONS_FILE
    annotated = annotations_path.is_file()
    mvdnet = isinstance(listing.polar, NativeSource) and (folder / MVDNET_LABELS).is_dir() and not annotated
    if mvdnet:
        annotated = True
        objects = _mvdnet_objects(folder, numbers, listing.timestamp_texts, image_size, resolution)
    elif annotated:
        by_stamp = None
        if isinstance(listing.polar, NativeSource):  # native scans are named by their UNIX microseconds
            by_stamp = {int(text.replace(".", "")) // 1000: n for n, text in zip(numbers, listing.timestamp_texts)}
        objects = read_annotations(annotations_path, numbers, image_size, resolution, by_stamp)
    else:
        log.warning("%s not found: the %d frames carry no objects", annotations_path, len(numbers))
        objects = {n: [] for n in numbers}
    if annotated and LABELLED_AREA_KEY in meta:
        _ignore_outside_labelled_area(objects, meta[LABELLED_AREA_KEY], folder, image_size, resolution)
    frames = [
        RadarFrame(n, t, p, objects[n], listing.polar, text)
        for n, t, p, text in zip(numbers, stamps, listing.image_paths, listing.timestamp_texts)
    ]

    poses_path = folder / POSES_FILE
    poses: np.ndarray | None = None
    pose_source: str | None = None
    ground_truth = folder / GROUND_TRUTH_ODOMETRY
    if poses_path.exists():
        poses, pose_source = _file_poses(poses_path, numbers, stamps), "file"
    elif isinstance(listing.polar, NativeSource) and ground_truth.is_file():
        microseconds = [int(text.replace(".", "")) // 1000 for text in listing.timestamp_texts]
        poses, pose_source = read_ground_truth_odometry(ground_truth, microseconds), "file"
    elif estimate_poses:
        from rafd.data.odometry import estimate_sequence_poses  # opencv only; imported here to keep the reader light

        start = time.perf_counter()
        poses = estimate_sequence_poses((frame.load() for frame in frames), resolution)
        pose_source = "odometry"
        log.info(
            "%s: no %s; ego poses of %d frames estimated by radar odometry in %.1f s "
            "(run `rafd-odometry %s` to save them)",
            folder,
            POSES_FILE,
            len(frames),
            time.perf_counter() - start,
            folder,
        )
    else:
        log.info("%s: no %s and odometry not requested: sequence without poses", folder, POSES_FILE)
    return RadarSequence(
        name=str(meta.get("name") or folder.name),
        split=meta.get("set"),
        path=folder,
        frames=frames,
        poses=poses,
        pose_source=pose_source,
        image_size=image_size,
        resolution=resolution,
        annotated=annotated,
        condition=meta_condition(meta),
    )
