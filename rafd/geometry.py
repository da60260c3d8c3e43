"""Numpy-only geometry in RADIATE's convention: pixels <-> metres, SE(2) poses, oriented boxes.

Conventions (used everywhere: model outputs, targets, metrics, service):
- Continuous pixel coordinates (u, v): pixel column i covers [i, i + 1); the radar sits at the
  image centre (576, 576) of a full 1152x1152 scan, (S/2, S/2) of an S x S centre crop.
- Ego metres: x = (u - c) * res (right), y = (c - v) * res (forward = image up).
- Box (x, y, width, length, yaw): corners (x, y) + R(yaw) @ (+-width/2, +-length/2), R the
  counter-clockwise rotation in the ego frame. width runs along ego x, length along ego y at yaw 0.
- Pose (x, y, yaw): the ego frame's origin and heading in a fixed world frame,
  world = R(yaw) @ ego + (x, y).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

RADIATE_RESOLUTION = 0.173611  # metres per pixel of RADIATE's Cartesian Navtech scans
RADIATE_SCAN_SIZE = 1152  # pixels per side of a full Cartesian scan

# Unit-box corner signs in the order that maps onto RADIATE's pixel polygon
# [x0, y0], [x0 + w, y0], [x0 + w, y0 + h], [x0, y0 + h] (image y points down, ego y up).
_CORNER_SIGNS = np.array([[-1.0, 1.0], [1.0, 1.0], [1.0, -1.0], [-1.0, -1.0]])


def rotation_matrix(yaw: np.ndarray | float) -> np.ndarray:
    """[...] -> [..., 2, 2] counter-clockwise rotations."""
    yaw = np.asarray(yaw, dtype=np.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def wrap_angle(angle: np.ndarray | float) -> np.ndarray:
    """Wrap to [-pi, pi)."""
    return (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi


# ---------------------------------------------------------------- pixels <-> metres
def pixels_to_metres(uv: np.ndarray, image_size: int, resolution: float = RADIATE_RESOLUTION) -> np.ndarray:
    """[..., 2] (u, v) continuous pixels of a square image centred on the radar -> [..., 2] (x, y) metres."""
    uv = np.asarray(uv, dtype=np.float64)
    centre = image_size / 2.0
    return np.stack([(uv[..., 0] - centre) * resolution, (centre - uv[..., 1]) * resolution], -1)


def metres_to_pixels(xy: np.ndarray, image_size: int, resolution: float = RADIATE_RESOLUTION) -> np.ndarray:
    """[..., 2] (x, y) metres -> [..., 2] (u, v) continuous pixels of a square image centred on the radar."""
    xy = np.asarray(xy, dtype=np.float64)
    centre = image_size / 2.0
    return np.stack([xy[..., 0] / resolution + centre, centre - xy[..., 1] / resolution], -1)


def centre_crop(image: np.ndarray, size: int) -> np.ndarray:
    """[H, W, ...] -> [size, size, ...] around the image centre (the radar)."""
    height, width = image.shape[:2]
    if size > height or size > width:
        raise ValueError(f"cannot crop {size}x{size} from a {height}x{width} image")
    top, left = (height - size) // 2, (width - size) // 2
    return image[top : top + size, left : left + size]


def feature_cell_centres(feature_size: int, input_size: int, resolution: float) -> np.ndarray:
    """[Hf, Wf, 2] metres of each feature cell's centre (row i, column j) in the ego frame."""
    stride = input_size / feature_size
    centres = (np.arange(feature_size) + 0.5) * stride
    u, v = np.meshgrid(centres, centres, indexing="xy")
    return pixels_to_metres(np.stack([u, v], -1), input_size, resolution)


# ---------------------------------------------------------------- SE(2) poses
def pose_to_matrix(pose: np.ndarray) -> np.ndarray:
    """[..., 3] (x, y, yaw) -> [..., 3, 3] homogeneous ego -> world transforms."""
    pose = np.asarray(pose, dtype=np.float64)
    matrix = np.zeros(pose.shape[:-1] + (3, 3))
    matrix[..., :2, :2] = rotation_matrix(pose[..., 2])
    matrix[..., :2, 2] = pose[..., :2]
    matrix[..., 2, 2] = 1.0
    return matrix


def matrix_to_pose(matrix: np.ndarray) -> np.ndarray:
    """[..., 3, 3] -> [..., 3] (x, y, yaw)."""
    matrix = np.asarray(matrix, dtype=np.float64)
    yaw = np.arctan2(matrix[..., 1, 0], matrix[..., 0, 0])
    return np.concatenate([matrix[..., :2, 2], yaw[..., None]], -1)


def compose_poses(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """first o second: apply `second`, then `first` ([..., 3] each)."""
    return matrix_to_pose(pose_to_matrix(first) @ pose_to_matrix(second))


def invert_pose(pose: np.ndarray) -> np.ndarray:
    """[..., 3] -> [..., 3], the inverse rigid motion."""
    return matrix_to_pose(np.linalg.inv(pose_to_matrix(pose)))


def relative_pose(pose_from: np.ndarray, pose_to: np.ndarray) -> np.ndarray:
    """[..., 3] world poses -> [..., 3], the pose mapping points of the `pose_from` ego frame into the `pose_to` ego
    frame: invert(to) o from, yaw wrapped to (-pi, pi]. The one definition (the service's windows and odometry, the
    evaluation); rafd.model.align.relative_pose_torch is its in-graph twin. Differences are taken before rotating, so
    large world coordinates (UTM metres) lose no precision."""
    pose_from = np.asarray(pose_from, dtype=np.float64)
    pose_to = np.asarray(pose_to, dtype=np.float64)
    dx = pose_from[..., 0] - pose_to[..., 0]
    dy = pose_from[..., 1] - pose_to[..., 1]
    cos_to, sin_to = np.cos(pose_to[..., 2]), np.sin(pose_to[..., 2])
    dyaw = pose_from[..., 2] - pose_to[..., 2]
    return np.stack([cos_to * dx + sin_to * dy, -sin_to * dx + cos_to * dy, np.arctan2(np.sin(dyaw), np.cos(dyaw))], -1)


def transform_points(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply one pose [3] to points [..., 2]: R(yaw) @ p + (x, y)."""
    pose = np.asarray(pose, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64)
    return points @ rotation_matrix(pose[2]).T + pose[:2]


# ---------------------------------------------------------------- oriented boxes
def box_corners(boxes: np.ndarray) -> np.ndarray:
    """[N, 5] (x, y, width, length, yaw) -> [N, 4, 2] corners in metres (RADIATE polygon order)."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 5)
    half = boxes[:, None, 2:4] / 2.0 * _CORNER_SIGNS[None]  # [N, 4, 2]
    rotated = np.einsum("nij,nkj->nki", rotation_matrix(boxes[:, 4]), half)
    return rotated + boxes[:, None, :2]


def points_in_boxes(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """[N, 2] points and [M, 5] boxes (metres) -> [N, M] bool: the point lies inside the box (edges included)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 5)
    d = points[:, None, :] - boxes[None, :, :2]  # [N, M, 2]
    c, s = np.cos(boxes[:, 4]), np.sin(boxes[:, 4])  # [M]
    local_x = c * d[..., 0] + s * d[..., 1]  # R(-yaw) d: along the box's width axis
    local_y = -s * d[..., 0] + c * d[..., 1]
    return (np.abs(local_x) <= boxes[:, 2] / 2.0) & (np.abs(local_y) <= boxes[:, 3] / 2.0)


def box_polygons_pixels(boxes: np.ndarray, image_size: int, resolution: float = RADIATE_RESOLUTION) -> np.ndarray:
    """[N, 5] metre boxes -> [N, 4, 2] corner pixels (u, v) of a square image centred on the radar."""
    return metres_to_pixels(box_corners(boxes), image_size, resolution)


def radiate_polygon(position: Sequence[float] | np.ndarray, rotation_deg: float) -> np.ndarray:
    """RADIATE SDK construction: corners of the unrotated [x0, y0, w, h] box rotated about its
    centre by R(deg2rad(-rotation)) in pixel coordinates. Returns [4, 2] (u, v)."""
    x0, y0, w, h = (float(p) for p in position)
    corners = np.array([[x0, y0], [x0 + w, y0], [x0 + w, y0 + h], [x0, y0 + h]])
    centre = np.array([x0 + w / 2.0, y0 + h / 2.0])
    return (corners - centre) @ rotation_matrix(np.deg2rad(-rotation_deg)).T + centre


def radiate_to_box(
    position: Sequence[float] | np.ndarray,
    rotation_deg: float,
    image_size: int = RADIATE_SCAN_SIZE,
    resolution: float = RADIATE_RESOLUTION,
) -> np.ndarray:
    """RADIATE annotation (position [x0, y0, w, h] in pixels, rotation in degrees) -> box [5] in metres."""
    x0, y0, w, h = (float(p) for p in position)
    centre = pixels_to_metres(np.array([x0 + w / 2.0, y0 + h / 2.0]), image_size, resolution)
    return np.array([centre[0], centre[1], w * resolution, h * resolution, np.deg2rad(rotation_deg)])


def box_to_radiate(
    box: np.ndarray, image_size: int = RADIATE_SCAN_SIZE, resolution: float = RADIATE_RESOLUTION
) -> tuple[list[float], float]:
    """Inverse of `radiate_to_box`: box [5] metres -> (position [x0, y0, w, h] pixels, rotation degrees)."""
    x, y, width, length, yaw = (float(b) for b in box)
    u, v = metres_to_pixels(np.array([x, y]), image_size, resolution)
    w, h = width / resolution, length / resolution
    return [float(u - w / 2.0), float(v - h / 2.0), w, h], float(np.rad2deg(yaw))
