"""Candidate vehicle returns on a Cartesian scan, for a person labelling it (rafd-label propose).

Not a detector: a generous proposer, so that the labeller looks at every compact bright return of about a
vehicle's size and decides. The scan's slowly varying background (a 6 m blur) is removed, what stands out by more
than `contrast` grey levels forms blobs (8-connected), and a blob is proposed when its area and its longest side fit a
vehicle's return (RADIATE's annotators box the whole blurred return: about 2.5-4 m x 4-7 m for a car, up to 18 m for
a bus) within `max_range_m` of the radar. Long thin blobs (walls, kerbs) and specks are not proposed.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from rafd.geometry import RADIATE_RESOLUTION, pixels_to_metres

MIN_AREA_M2 = 1.5  # smaller: speckle or a pole
MAX_AREA_M2 = 60.0  # larger: a building front
MAX_LENGTH_M = 20.0  # a bus's return
MAX_ELONGATION = 6.0  # length / width: walls and kerbs are longer and thinner


@dataclass(frozen=True)
class Candidate:
    index: int  # 1.. in order of distance from the radar
    x: float  # metres right of the radar
    y: float  # metres forward
    width: float  # metres, the blob's minimum-area rectangle
    length: float
    yaw_deg: float  # the rectangle's orientation, counter-clockwise (rafd.geometry's box convention)
    peak: int  # brightest grey level of the blob
    area_m2: float


def propose(
    scan: np.ndarray, resolution: float = RADIATE_RESOLUTION, max_range_m: float = 40.0, contrast: float = 18.0
) -> list[Candidate]:
    """uint8 [N, N] scan (radar at the centre) -> candidate returns, nearest first."""
    image = np.asarray(scan, dtype=np.float32)
    size = image.shape[0]
    smooth = cv2.GaussianBlur(image, (0, 0), 1.0)
    background = cv2.GaussianBlur(image, (0, 0), 6.0 / resolution)
    mask = ((smooth - background) > contrast).astype(np.uint8)
    count, labels, stats, centroids = cv2.connectedComponentsWithStats(mask, connectivity=8)
    pixel_m2 = resolution * resolution
    found = []
    for label in range(1, count):
        area = stats[label, cv2.CC_STAT_AREA] * pixel_m2
        if not MIN_AREA_M2 <= area <= MAX_AREA_M2:
            continue
        centre = pixels_to_metres(centroids[label] + 0.5, size, resolution)  # cv2 centroid of pixel indices
        if np.hypot(*centre) > max_range_m:
            continue
        points = np.argwhere(labels == label)[:, ::-1].astype(np.float32)  # (u, v)
        (_, _), (w_px, h_px), angle = cv2.minAreaRect(points)
        width, length = sorted((max(w_px, 1.0) * resolution, max(h_px, 1.0) * resolution))
        if length > MAX_LENGTH_M or length / width > MAX_ELONGATION:
            continue
        # cv2's angle is clockwise in the image for the rectangle's first side; the box convention is the yaw of the
        # width axis from ego x, counter-clockwise (image y points down, so the sign flips)
        yaw = -angle if w_px <= h_px else -(angle + 90.0)
        peak = int(smooth[labels == label].max())
        found.append((float(np.hypot(*centre)), centre, width, length, ((yaw + 90.0) % 180.0) - 90.0, peak, area))
    found.sort(key=lambda item: item[0])
    return [
        Candidate(k + 1, float(c[0]), float(c[1]), w, ln, y, p, a) for k, (_, c, w, ln, y, p, a) in enumerate(found)
    ]
