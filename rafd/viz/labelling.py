"""Pictures for a person labelling scans (rafd-label): an overview of a scan with its candidate returns numbered, and
per candidate a zoomed sheet of the previous, current and next scans, the neighbours moved into the current scan's
ego frame (by the sequence's poses) so that the static world stands still and a moving vehicle moves."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from rafd.data.candidates import Candidate
from rafd.geometry import RADIATE_RESOLUTION, box_polygons_pixels, metres_to_pixels, relative_pose
from rafd.odometry.registration import pose_to_warp

GRID_M = 5.0  # a grid line every 5 m
CANDIDATE_COLOUR = (0, 200, 255)  # BGR: amber
LABEL_COLOUR = (80, 255, 80)
IGNORE_COLOUR = (200, 200, 200)


def stretched(scan: np.ndarray, gain: float = 2.5) -> np.ndarray:
    """Grey scan -> BGR with the dim returns brightened (radar scans are dark), clipped at white."""
    bright = np.clip(np.asarray(scan, np.float32) * gain, 0, 255).astype(np.uint8)
    return cv2.cvtColor(bright, cv2.COLOR_GRAY2BGR)


def into_frame(scan: np.ndarray, pose: np.ndarray, reference: np.ndarray, resolution: float) -> np.ndarray:
    """Scan taken at world `pose`, resampled into the ego frame of world pose `reference` (same grid)."""
    size = scan.shape[0]
    warp = pose_to_warp(relative_pose(reference, pose), size, resolution)  # the reference ego in the scan's frame
    return cv2.warpAffine(scan, warp, (size, size), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)


def _grid(image: np.ndarray, size: int, resolution: float, origin: tuple[int, int], zoom: int) -> None:
    """Grid lines every GRID_M metres of the ego frame on a zoomed window whose top-left scan pixel is `origin`."""
    height, width = image.shape[:2]
    for metres in np.arange(-100.0, 100.0 + 1e-9, GRID_M):
        u, v = metres_to_pixels(np.array([metres, metres]), size, resolution)
        x, y = int((u - origin[0]) * zoom), int((v - origin[1]) * zoom)
        colour = (90, 90, 90) if metres else (160, 160, 160)
        if 0 <= x < width:
            cv2.line(image, (x, 0), (x, height - 1), colour, 1)
        if 0 <= y < height:
            cv2.line(image, (0, y), (width - 1, y), colour, 1)


def window(
    scan: np.ndarray, centre_m: tuple[float, float], half_m: float, zoom: int, resolution: float = RADIATE_RESOLUTION
) -> tuple[np.ndarray, tuple[int, int]]:
    """BGR zoomed window of `half_m` around a point (metres) -> (image, top-left scan pixel)."""
    size = scan.shape[0]
    u, v = metres_to_pixels(np.array(centre_m), size, resolution)
    half = int(round(half_m / resolution))
    left, top = int(round(u)) - half, int(round(v)) - half
    padded = np.zeros((2 * half, 2 * half), scan.dtype)
    src = scan[max(top, 0) : min(top + 2 * half, size), max(left, 0) : min(left + 2 * half, size)]
    padded[max(-top, 0) : max(-top, 0) + src.shape[0], max(-left, 0) : max(-left, 0) + src.shape[1]] = src
    image = cv2.resize(stretched(padded), None, fx=zoom, fy=zoom, interpolation=cv2.INTER_NEAREST)
    _grid(image, size, resolution, (left, top), zoom)
    return image, (left, top)


def candidate_sheet(
    scans: Sequence[np.ndarray | None],
    candidate: Candidate,
    titles: Sequence[str],
    half_m: float = 12.0,
    zoom: int = 4,
    resolution: float = RADIATE_RESOLUTION,
) -> np.ndarray:
    """Previous / current / next scans (already in the current ego frame; None where absent) around a candidate,
    side by side, the candidate's rectangle drawn on the current one."""
    panels = []
    for scan, title in zip(scans, titles):
        if scan is None:
            size = int(round(2 * half_m / resolution)) * zoom
            panel = np.zeros((size, size, 3), np.uint8)
        else:
            panel, origin = window(scan, (candidate.x, candidate.y), half_m, zoom, resolution)
            if title.startswith("current"):
                box = np.array(
                    [[candidate.x, candidate.y, candidate.width, candidate.length, np.radians(candidate.yaw_deg)]]
                )
                corners = (box_polygons_pixels(box, scan.shape[0], resolution)[0] - origin) * zoom
                cv2.polylines(panel, [np.round(corners).astype(np.int32)], True, CANDIDATE_COLOUR, 1, cv2.LINE_AA)
        cv2.putText(panel, title, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
        panels.append(panel)
    sheet = np.concatenate(panels, axis=1)
    text = (
        f"candidate {candidate.index}: x {candidate.x:+.1f} m, y {candidate.y:+.1f} m, "
        f"{candidate.width:.1f} x {candidate.length:.1f} m, yaw {candidate.yaw_deg:+.0f} deg, "
        f"peak {candidate.peak}; "
        f"grid {GRID_M:g} m"
    )
    footer = np.zeros((30, sheet.shape[1], 3), np.uint8)
    cv2.putText(footer, text, (8, 21), cv2.FONT_HERSHEY_SIMPLEX, 0.55, (255, 255, 255), 1, cv2.LINE_AA)
    return np.concatenate([sheet, footer], axis=0)


def overview(
    scan: np.ndarray,
    candidates: Sequence[Candidate],
    boxes: np.ndarray | None = None,
    classes: Sequence[str] = (),
    half_m: float = 40.0,
    zoom: int = 2,
    resolution: float = RADIATE_RESOLUTION,
) -> np.ndarray:
    """The scan around the radar with the candidates numbered and, optionally, labelled boxes [M, 5] drawn."""
    image, origin = window(scan, (0.0, 0.0), half_m, zoom, resolution)
    size = scan.shape[0]
    for candidate in candidates:
        u, v = metres_to_pixels(np.array([candidate.x, candidate.y]), size, resolution)
        point = (int((u - origin[0]) * zoom), int((v - origin[1]) * zoom))
        cv2.circle(image, point, 10, CANDIDATE_COLOUR, 1, cv2.LINE_AA)
        cv2.putText(
            image,
            str(candidate.index),
            (point[0] + 11, point[1] - 6),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.45,
            CANDIDATE_COLOUR,
            1,
            cv2.LINE_AA,
        )
    if boxes is not None and len(boxes):
        corners = (box_polygons_pixels(boxes, size, resolution) - origin) * zoom
        for polygon, name in zip(corners, list(classes) + [""] * len(corners)):
            colour = IGNORE_COLOUR if name == "ignore" else LABEL_COLOUR
            cv2.polylines(image, [np.round(polygon).astype(np.int32)], True, colour, 1, cv2.LINE_AA)
    return image
