"""Scan statistics used to match the simulator's difficulty knobs to real RADIATE scans."""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np

from rafd.geometry import RADIATE_SCAN_SIZE, radiate_polygon

BRIGHT_LEVEL = 100  # grey level above which a pixel counts as a strong return


@dataclass(frozen=True)
class ScanStatistics:
    p50: float  # intensity percentiles over the scan disc
    p90: float
    p99: float
    bright_fraction: float  # share of disc pixels > BRIGHT_LEVEL
    contrast: float  # mean intensity inside annotated boxes / mean outside (nan without boxes)

    def as_dict(self) -> dict[str, float]:
        return {k: round(v, 4) for k, v in asdict(self).items()}


def scan_disc_mask(size: int) -> np.ndarray:
    """[S, S] bool: pixels whose centre lies inside the radar's 576-pixel scan disc (2 px margin)."""
    centres = np.arange(size) + 0.5 - size / 2.0
    return np.hypot(*np.meshgrid(centres, centres)) < RADIATE_SCAN_SIZE / 2.0 - 2.0


def scan_statistics(images: Sequence[np.ndarray], polygons_per_image: Sequence[Sequence[np.ndarray]]) -> ScanStatistics:
    """uint8 [S, S] scans and, per scan, [4, 2] pixel polygons of its annotated objects -> statistics."""
    if len(images) == 0 or len(images) != len(polygons_per_image):
        raise ValueError(f"need one polygon list per image, got {len(images)} images and {len(polygons_per_image)} lists")
    disc = scan_disc_mask(images[0].shape[0])
    values, inside_sum, inside_n, outside_sum, outside_n = [], 0.0, 0, 0.0, 0
    for image, polygons in zip(images, polygons_per_image):
        boxes = np.zeros(image.shape, np.uint8)
        for polygon in polygons:
            cv2.fillPoly(boxes, [np.round(np.asarray(polygon)).astype(np.int32)], 1)
        inside, outside = disc & (boxes > 0), disc & (boxes == 0)
        inside_sum += float(image[inside].sum())
        inside_n += int(inside.sum())
        outside_sum += float(image[outside].sum())
        outside_n += int(outside.sum())
        values.append(image[disc])
    pixels = np.concatenate(values)
    p50, p90, p99 = np.percentile(pixels, [50, 90, 99])
    contrast = (inside_sum / inside_n) / (outside_sum / outside_n) if inside_n and outside_n else float("nan")
    return ScanStatistics(float(p50), float(p90), float(p99), float((pixels > BRIGHT_LEVEL).mean()), float(contrast))


def sequence_statistics(sequence_dir: Path, max_frames: int | None = None) -> ScanStatistics:
    """Statistics of a RADIATE-format folder (real or simulated), boxes from its annotations.json."""
    sequence_dir = Path(sequence_dir)
    paths = sorted((sequence_dir / "Navtech_Cartesian").glob("*.png"))[:max_frames]
    if not paths:
        raise FileNotFoundError(f"no scans in {sequence_dir / 'Navtech_Cartesian'}")
    annotations = json.loads((sequence_dir / "annotations" / "annotations.json").read_text())
    images, polygons = [], []
    for path in paths:
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise OSError(f"could not read {path}")
        index = int(path.stem) - 1
        images.append(image)
        polygons.append(
            [
                radiate_polygon(obj["bboxes"][index]["position"], obj["bboxes"][index]["rotation"])
                for obj in annotations
                if index < len(obj["bboxes"]) and obj["bboxes"][index]
            ]
        )
    return scan_statistics(images, polygons)
