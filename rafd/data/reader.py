"""Read one sequence folder (RADIATE's layout, real or simulated, polar-only, or Oxford / Boreas native) into a
RadarSequence: its frames (rafd.data.folders lists and checks the scans), their objects and the ego poses.

Objects come from annotations/annotations.json (rafd.data.radiate_files; keyed by scan timestamps in native folders),
else from a native folder's MVDNet labels (rafd.data.mvdnet_labels), else there are none (a log warning); meta.json's
labelled_half_m adds ignore regions outside the labelled square. Poses come from ego_poses.csv ("file"), else from a
native folder's ground-truth odometry ("file"), else from radar odometry ("odometry", logged), never silently
identity. Bad data raises FileNotFoundError/ValueError naming the file.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from rafd.data.folders import ANNOTATIONS_FILE, META_FILE, list_frames
from rafd.data.frames import RadarFrame, RadarObject, RadarSequence
from rafd.data.labels import IGNORE_CLASS, LABELLED_AREA_KEY, outside_square
from rafd.data.mvdnet_labels import MVDNET_LABELS, mvdnet_objects
from rafd.data.native_folder import GROUND_TRUTH_ODOMETRY, read_ground_truth_odometry, text_microseconds
from rafd.data.poses import POSES_FILE, read_frame_poses
from rafd.data.radiate_files import meta_condition, read_annotations
from rafd.geometry import RADIATE_RESOLUTION, RADIATE_SCAN_SIZE, box_polygons_pixels
from rafd.scans.native import NativeSource

log = logging.getLogger(__name__)


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
    """One sequence folder, or a ROS 2 bag (rafd.ros.sequence), -> RadarSequence. estimate_poses=False skips odometry
    when the folder has no ego_poses.csv (poses None, pose_source None): for tools that only need frames and
    annotations."""
    from rafd.ros.sequence import is_bag

    if is_bag(path):
        return read_bag_sequence(Path(path), estimate_poses)
    listing = list_frames(path)
    folder, numbers, stamps = listing.folder, listing.numbers, listing.timestamps
    image_size, resolution, meta = listing.image_size, listing.resolution, listing.meta

    annotations_path = folder / ANNOTATIONS_FILE
    annotated = annotations_path.is_file()
    mvdnet = isinstance(listing.polar, NativeSource) and (folder / MVDNET_LABELS).is_dir() and not annotated
    if mvdnet:
        annotated = True
        objects = mvdnet_objects(folder, numbers, listing.timestamp_texts, image_size, resolution)
    elif annotated:
        by_stamp = None
        if isinstance(listing.polar, NativeSource):  # native scans are named by their UNIX microseconds
            by_stamp = {text_microseconds(text): n for n, text in zip(numbers, listing.timestamp_texts)}
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
        poses, pose_source = read_frame_poses(poses_path, numbers, stamps), "file"
    elif isinstance(listing.polar, NativeSource) and ground_truth.is_file():
        microseconds = [text_microseconds(text) for text in listing.timestamp_texts]
        poses, pose_source = read_ground_truth_odometry(ground_truth, microseconds), "file"
    elif estimate_poses:
        from rafd.odometry.registration import (
            estimate_sequence_poses,  # opencv only; imported here to keep the reader light
        )

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


def nanoseconds_text(nanoseconds: int) -> str:
    """UNIX nanoseconds -> the canonical 'seconds.nnnnnnnnn' text (exact)."""
    return f"{nanoseconds // 1_000_000_000}.{nanoseconds % 1_000_000_000:09d}"


def read_bag_sequence(bag: Path, estimate_poses: bool = True) -> RadarSequence:
    """A ROS 2 bag's scan topic (found by type) -> RadarSequence: frames 1..N at their header stamps, no labels,
    poses from `<bag>.ego_poses.csv` beside it, else radar odometry when asked for."""
    from rafd.ros.sequence import BagScanSource, bag_frames, poses_file

    topic, listed = bag_frames(bag)
    frames = [
        RadarFrame(n, stamp / 1e9, bag, [], BagScanSource(topic, log, stamp), nanoseconds_text(stamp))
        for n, (log, stamp) in enumerate(listed, 1)
    ]
    numbers = [frame.number for frame in frames]
    poses: np.ndarray | None = None
    pose_source: str | None = None
    if poses_file(bag).is_file():
        poses, pose_source = read_frame_poses(poses_file(bag), numbers, [f.timestamp for f in frames]), "file"
    elif estimate_poses and frames:
        from rafd.odometry.registration import estimate_sequence_poses

        poses = estimate_sequence_poses((frame.load() for frame in frames), RADIATE_RESOLUTION)
        pose_source = "odometry"
        log.info(
            "%s: ego poses of %d scans estimated by radar odometry (rafd odometry BAG saves them)", bag, len(frames)
        )
    log.info("%s: %d scans on %s (%s); a bag carries no labels", bag, len(frames), topic.topic, topic.msgtype)
    return RadarSequence(
        name=bag.stem if bag.is_file() else bag.name,
        split=None,
        path=bag,
        frames=frames,
        poses=poses,
        pose_source=pose_source,
        image_size=RADIATE_SCAN_SIZE,
        resolution=RADIATE_RESOLUTION,
        annotated=False,
        condition=None,
    )
