"""The three layouts of a sequence folder, and its scans listed and checked against its files (FrameList): frame
numbers, timestamps, scan paths, the side and resolution of the Cartesian scans they give, and meta.json.

    Navtech_Cartesian/000001.png ...   Cartesian (RADIATE's): uint8 grey scans, radar at the image centre
    Navtech_Cartesian.txt              their timestamps (rafd.data.radiate_files.read_timestamps)
    Navtech_Polar/000001.png ...       polar-only: instead of the two above, the sensor's polar scans uint8 [576, 400]
    Navtech_Polar.txt                  (+ their timestamps), converted on load (rafd.scans.polar.PolarSource)
    radar/<microseconds>.png ...       native: the scans in the sensor's own layout (Oxford Radar RobotCar, Boreas;
                                       rafd.data.native_folder), converted on load (rafd.scans.native.NativeSource)
    annotations/annotations.json      the labels, meta.json the split and sizes (rafd.data.radiate_files)
    annotations/velocities.json       simulated drives only: each labelled road user's true ground velocity
                                       (rafd.sim.writer.velocities_json; read by rafd.eval.velocity_truth)
    ego_poses.csv                      optional, ours (rafd.data.poses): frame, timestamp, x, y, yaw

A folder with both Cartesian and polar scans (RADIATE ships both) is read from its Cartesian scans; a polar-only
folder gives scans of meta.json "image_size" pixels (default: the whole polar disc, 1152 for RADIATE), a native one
of "image_size" (default 1152) at RADIATE's resolution; FrameList.load() converts each on load. Bad data raises
FileNotFoundError/ValueError naming the file.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rafd.data.native_folder import (
    check_native_png,
    is_native_folder,
    list_native_scans,
    microseconds_text,
    native_format_of,
)
from rafd.data.radiate_files import finite_number, read_meta, read_timestamps
from rafd.geometry import RADIATE_RESOLUTION, RADIATE_SCAN_SIZE
from rafd.scans.cartesian import load_image, png_size
from rafd.scans.native import NativeSource
from rafd.scans.polar import RADIATE_POLAR, PolarSource, cartesian_size

log = logging.getLogger(__name__)

IMAGE_DIR = "Navtech_Cartesian"
TIMESTAMPS_FILE = "Navtech_Cartesian.txt"
POLAR_DIR = "Navtech_Polar"
POLAR_TIMESTAMPS_FILE = "Navtech_Polar.txt"
ANNOTATIONS_FILE = "annotations/annotations.json"
VELOCITIES_FILE = "annotations/velocities.json"
META_FILE = "meta.json"

_IMAGE_NAME = re.compile(r"(\d+)\.png")


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
        resolution = finite_number(meta["resolution"], meta_path, "resolution")
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
    source = NativeSource(native_format_of(meta, *scans[0]), image_size, RADIATE_RESOLUTION)
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
