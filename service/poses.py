"""Which world pose a frame gets: the request's, or odometry from the radar composed onto the previous pose.

Rule (documented in the API): a stream's FIRST frame fixes its world frame. A stream started with request
poses may omit the pose on a later frame (e.g. a GNSS dropout): that frame's pose is odometry composed
onto the previous frame's pose, in the same world frame. A stream started without a pose lives in an
odometry world frame anchored at its first frame (pose 0, 0, 0), so a later request pose would be in an
unrelated frame: that is refused with 409 (delete the stream to switch).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from rafd.geometry import centre_crop, compose_poses
from service.errors import ApiError

# (previous [S, S], current [S, S], resolution m/px) -> [3] current ego pose in the previous ego frame
Odometry = Callable[[np.ndarray, np.ndarray, float], np.ndarray]


def default_odometry() -> Odometry:
    """rafd.data.odometry.estimate_relative_pose, imported on first use (never at service import)."""
    try:
        from rafd.data.odometry import estimate_relative_pose
    except ImportError as exc:
        raise ApiError(
            "odometry_unavailable", f"this build cannot estimate ego motion ({exc}); send a pose with every frame"
        ) from exc
    return estimate_relative_pose


def check_request_pose(stream_pose_source: str | None) -> None:
    """Refuse a request pose on a stream whose world frame was anchored by odometry."""
    if stream_pose_source == "odometry":
        raise ApiError(
            "pose_source_conflict",
            "this stream started without poses (odometry world frame anchored at its first frame); "
            "a request pose would be in another world frame: DELETE the stream to switch to poses",
        )


def odometry_pose(
    previous_pose: np.ndarray | None,
    previous_frame: np.ndarray | None,
    frame: np.ndarray,
    resolution: float,
    odometry: Odometry,
) -> np.ndarray:
    """[3] world pose of `frame`: (0, 0, 0) for a stream's first frame, else previous pose o relative motion."""
    if previous_pose is None or previous_frame is None:
        return np.zeros(3)
    if previous_frame.shape != frame.shape:  # a stream switched between full scans and model-size crops
        side = min(previous_frame.shape[0], frame.shape[0])
        previous_frame, frame = centre_crop(previous_frame, side), centre_crop(frame, side)
    relative = np.asarray(odometry(previous_frame, frame, resolution), dtype=np.float64)
    if relative.shape != (3,) or not np.all(np.isfinite(relative)):
        raise ApiError("odometry_failed", f"odometry returned {relative!r}; expected 3 finite numbers")
    return compose_poses(previous_pose, relative)
