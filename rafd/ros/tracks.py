"""What one answered box says about its object, for radar_msgs/RadarTrack and vision_msgs/Detection3D: an id, a UUID,
the velocity and its covariance in REP-103 axes, NaN where unknown.

The service's tracking fields (when it answers them): `track_id` (a string, unique within a stream), `velocity`
{"x", "y"} (ground velocity, m/s, service axes) or null, `velocity_covariance` [[xx, xy], [xy, yy]] (m/s)^2 or null,
`velocity_source` ("flow" | "track" | "none"), `track` {"status", "age", "hits"}. Without them (a service without
tracking) every box is its own object: its id and UUID come from the stream, the scan's time and the box's place in
the answer, so no two boxes share one, as radar_msgs' authors ask of a sensor without tracking
(ros-perception/radar_msgs#2), and the velocity and every covariance are NaN ("not supported by the sensor").

UUIDs are name-based (UUID version 5) in rafd's own namespace: from `<stream>/track/<track_id>` for a tracked box
(the same track keeps its UUID from scan to scan), from `<stream>/scan/<stamp ns>/box/<index>` otherwise.
"""

from __future__ import annotations

import math
import uuid
from dataclasses import dataclass
from typing import Any

import numpy as np

from rafd.ros.axes import covariance_to_ros, position_to_ros

# rafd's UUID namespace (uuid5 of the URL namespace and "rafd/ros/tracks"), fixed: UUIDs stay the same across versions.
TRACK_NAMESPACE = uuid.uuid5(uuid.NAMESPACE_URL, "rafd/ros/tracks")
NAN = float("nan")


@dataclass(frozen=True)
class TrackFields:
    """One box's identity and motion, ready for the ROS messages (REP-103 axes)."""

    id: str  # Detection3D.id: the track id, else the per-box name
    uuid: bytes  # 16 bytes: RadarTrack.uuid
    tracked: bool  # whether the service tracked the box (track_id given)
    velocity: tuple[float, float]  # m/s (x forward, y left); NaN when unknown
    velocity_covariance: np.ndarray  # [2, 2] (m/s)^2 in REP-103 axes; NaN when unknown
    velocity_source: str  # the service's velocity_source, "none" when it gives none
    status: str | None  # the service's track status (tentative / confirmed / coasting), None without tracking


def _finite_pair(value: Any) -> tuple[float, float] | None:
    if not isinstance(value, dict):
        return None
    try:
        x, y = float(value["x"]), float(value["y"])
    except (KeyError, TypeError, ValueError):
        return None
    return (x, y) if math.isfinite(x) and math.isfinite(y) else None


def _covariance(value: Any) -> np.ndarray | None:
    try:
        matrix = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return None
    if matrix.shape != (2, 2) or not np.all(np.isfinite(matrix)):
        return None
    return matrix


def track_fields(box: dict[str, Any], stream_id: str, stamp_ns: int, index: int) -> TrackFields:
    """An answered box (`index` in its answer, the scan stamped `stamp_ns`, on `stream_id`) -> TrackFields."""
    track_id = box.get("track_id")
    if track_id is not None and str(track_id) != "":
        name = f"{stream_id}/track/{track_id}"
        box_id, tracked = str(track_id), True
    else:
        name = f"{stream_id}/scan/{int(stamp_ns)}/box/{int(index)}"
        box_id, tracked = name, False
    velocity = _finite_pair(box.get("velocity"))
    covariance = _covariance(box.get("velocity_covariance")) if velocity is not None else None
    track = box.get("track")
    return TrackFields(
        id=box_id,
        uuid=uuid.uuid5(TRACK_NAMESPACE, name).bytes,
        tracked=tracked,
        velocity=(NAN, NAN) if velocity is None else position_to_ros(*velocity),
        velocity_covariance=np.full((2, 2), NAN) if covariance is None else covariance_to_ros(covariance),
        velocity_source=str(box.get("velocity_source") or "none") if velocity is not None else "none",
        status=str(track["status"]) if isinstance(track, dict) and "status" in track else None,
    )


def upper_triangle_3d(covariance_xy: np.ndarray, z: float = NAN) -> list[float]:
    """A [2, 2] covariance of x, y -> radar_msgs' float32[6] upper triangle about x, y, z ([xx, xy, xz, yy, yz, zz]),
    the z terms unknown (NaN) unless given: a scanning radar measures no height."""
    c = np.asarray(covariance_xy, dtype=np.float64)
    return [float(c[0, 0]), float(c[0, 1]), z, float(c[1, 1]), z, z]
