"""The service's axes -> ROS's (REP-103), written once: everything rafd writes into a bag goes through here.

The service answers in the radar's ego frame with x right, y forward, yaw counter-clockwise from x (seen from above),
a box's `width` along its own x axis and `length` along its own y axis (docs/api.md). REP-103 has x forward, y left,
z up, yaw counter-clockwise from x. Both are right-handed with z up: ROS's frame is the service's turned a quarter
turn clockwise, so

    ros_x = y,  ros_y = -x,  ros_yaw = yaw,  size.x = length,  size.y = width

(a box's length axis points at service angle pi/2 + yaw, which is ROS angle yaw), and a velocity turns like a
position. A covariance turns as R C R^T with R = [[0, 1], [-1, 0]]. The same holds for a world pose (the odometry
frame of a stream: its first frame's axes).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

# service (x, y) -> ROS (x, y): [[0, 1], [-1, 0]]
TO_ROS = np.array([[0.0, 1.0], [-1.0, 0.0]])


def position_to_ros(x: float, y: float) -> tuple[float, float]:
    """Service (x right, y forward) -> REP-103 (x forward, y left); a velocity too."""
    return float(y), float(-x)


def position_from_ros(ros_x: float, ros_y: float) -> tuple[float, float]:
    """REP-103 (x forward, y left) -> service (x right, y forward): position_to_ros's inverse."""
    return float(-ros_y), float(ros_x)


def covariance_to_ros(covariance: Sequence[Sequence[float]] | np.ndarray) -> np.ndarray:
    """[[xx, xy], [xy, yy]] in service axes -> the same in REP-103 axes ([[yy, -xy], [-xy, xx]])."""
    matrix = np.asarray(covariance, dtype=np.float64).reshape(2, 2)
    return TO_ROS @ matrix @ TO_ROS.T


def yaw_quaternion(yaw: float) -> tuple[float, float, float, float]:
    """A rotation of `yaw` about z (counter-clockwise from x) -> quaternion (x, y, z, w)."""
    return 0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0)


def quaternion_yaw(x: float, y: float, z: float, w: float) -> float:
    """A quaternion of a rotation about z -> its yaw (yaw_quaternion's inverse), in (-pi, pi]."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


@dataclass(frozen=True)
class RosBox:
    """An oriented box in REP-103 axes: centre (x forward, y left), yaw, size.x along its yaw, size.y across."""

    x: float
    y: float
    yaw: float
    size_x: float
    size_y: float


def box_to_ros(x: float, y: float, width: float, length: float, yaw: float) -> RosBox:
    """A service box (x, y, width, length, yaw) -> RosBox."""
    ros_x, ros_y = position_to_ros(x, y)
    return RosBox(ros_x, ros_y, float(yaw), float(length), float(width))


def box_from_ros(box: RosBox) -> tuple[float, float, float, float, float]:
    """RosBox -> the service's (x, y, width, length, yaw): box_to_ros's inverse."""
    x, y = position_from_ros(box.x, box.y)
    return x, y, box.size_y, box.size_x, box.yaw


def pose_to_ros(x: float, y: float, yaw: float) -> tuple[float, float, float]:
    """A world pose of the radar (service axes: world = R(yaw) @ ego + (x, y)) -> the same pose in the REP-103
    world frame (ros_x, ros_y, ros_yaw): the world frame turns like the ego frame."""
    ros_x, ros_y = position_to_ros(x, y)
    return ros_x, ros_y, float(yaw)
