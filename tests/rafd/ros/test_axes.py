"""The one conversion from the service's axes (x right, y forward) to REP-103 (x forward, y left)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rafd.geometry import box_corners
from rafd.ros.axes import (
    box_from_ros,
    box_to_ros,
    covariance_to_ros,
    pose_to_ros,
    position_to_ros,
    quaternion_yaw,
    yaw_quaternion,
)


def test_forward_is_ros_x_and_right_is_minus_ros_y():
    assert position_to_ros(0.0, 10.0) == (10.0, -0.0)  # 10 m ahead
    assert position_to_ros(3.0, 0.0) == (0.0, -3.0)  # 3 m to the right: negative y (left is +y)


def _ros_corners(ros) -> np.ndarray:
    """Corners of a ROS box: centre + R(yaw) @ (+-size_x/2, +-size_y/2) in REP-103 axes."""
    c, s = math.cos(ros.yaw), math.sin(ros.yaw)
    local = np.array([[sx * ros.size_x / 2, sy * ros.size_y / 2] for sx in (-1, 1) for sy in (-1, 1)])
    return local @ np.array([[c, s], [-s, c]]) + [ros.x, ros.y]


@pytest.mark.parametrize("yaw", [0.0, 0.3, -1.2, math.pi / 2, 2.9])
def test_a_box_keeps_its_corners(yaw: float):
    """The service's corners (rafd.geometry) turned into ROS axes are the ROS box's own corners."""
    box = np.array([4.0, 25.0, 1.8, 4.5, yaw])  # x, y, width, length, yaw
    service = box_corners(box[None])[0]  # [4, 2]
    turned = np.array([position_to_ros(*corner) for corner in service])
    ros = box_to_ros(*box)
    assert (ros.size_x, ros.size_y) == (4.5, 1.8) and ros.yaw == yaw
    expected = _ros_corners(ros)
    assert all(np.min(np.linalg.norm(expected - point, axis=1)) < 1e-9 for point in turned)
    np.testing.assert_allclose(box_from_ros(ros), box)


def test_a_vehicle_ahead_heading_forward_has_yaw_zero_and_its_length_along_x():
    """A service box with yaw 0 has its length along service y (forward): in ROS its size.x is the length, yaw 0."""
    ros = box_to_ros(0.0, 20.0, 1.8, 4.5, 0.0)
    assert (ros.x, ros.y, ros.yaw, ros.size_x, ros.size_y) == (20.0, -0.0, 0.0, 4.5, 1.8)


def test_quaternions_and_covariances():
    for yaw in (0.0, 0.7, -2.5, math.pi - 1e-6):
        assert quaternion_yaw(*yaw_quaternion(yaw)) == pytest.approx(yaw)
    covariance = np.array([[4.0, 1.0], [1.0, 9.0]])  # var x (right) 4, var y (forward) 9
    np.testing.assert_allclose(covariance_to_ros(covariance), [[9.0, -1.0], [-1.0, 4.0]])
    # a velocity turns like a position: the covariance of the turned samples is the turned covariance
    rng = np.random.default_rng(0)
    samples = rng.multivariate_normal([0, 0], covariance, 20000)
    turned = np.array([position_to_ros(*v) for v in samples])
    np.testing.assert_allclose(np.cov(turned.T), covariance_to_ros(np.cov(samples.T)), atol=1e-9)


def test_a_world_pose_turns_like_the_ego_frame():
    x, y, yaw = pose_to_ros(1.0, 5.0, 0.2)
    assert (x, y, yaw) == (5.0, -1.0, 0.2)
