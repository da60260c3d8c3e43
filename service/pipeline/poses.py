"""Which world pose a frame gets: the request's, or odometry from the radar composed onto the previous pose.

Rule (documented in the API): a stream's FIRST frame fixes its world frame. A stream started with request
poses may omit the pose on a later frame (e.g. a GNSS dropout): that frame's pose is odometry composed
onto the previous frame's pose, in the same world frame. A stream started without a pose lives in an
odometry world frame anchored at its first frame (pose 0, 0, 0), so a later request pose would be in an
unrelated frame: that is refused with 409 (delete the stream to switch).

Each stream keeps an OdometryMemory of its last accepted frame. By default it holds the stream's
rafd.odometry.registration.OdometryStream: each scan is prepared (levels, de-skew over the sweep) once and the previous
pair's motion narrows the next search, about half the CPU of registering every pair from scratch, and the sweep
is motion-compensated (the posted timestamps give the period; a native scan carries its own azimuth times). A
custom pairwise Odometry (tests, or a caller's own) registers (previous view, current view) instead.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from types import ModuleType
from typing import TYPE_CHECKING

import numpy as np

from rafd.geometry import centre_crop, compose_poses
from service.http.errors import ApiError

if TYPE_CHECKING:
    from rafd.odometry.registration import OdometryStream, SweepTiming

# (previous [S, S], current [S, S], resolution m/px) -> [3] current ego pose in the previous ego frame
Odometry = Callable[[np.ndarray, np.ndarray, float], np.ndarray]
# a native scan's (per-azimuth UNIX microseconds [A], azimuths in radians clockwise from forward [A])
Sweep = tuple[np.ndarray, np.ndarray]


@dataclass(frozen=True)
class OdometryMemory:
    """What a stream keeps of its last accepted frame for the next frame's odometry. Immutable: a frame's odometry
    makes a new memory, which the stream takes only when the frame is accepted."""

    view: np.ndarray  # [V, V] uint8 odometry view of the frame
    timestamp: float  # seconds
    sweep: Sweep | None = None  # a native scan's own azimuth times
    tracker: OdometryStream | None = None  # the stream's odometry with this frame as its previous scan (default path)


def check_request_pose(stream_pose_source: str | None) -> None:
    """Refuse a request pose on a stream whose world frame was anchored by odometry."""
    if stream_pose_source == "odometry":
        raise ApiError(
            "pose_source_conflict",
            "this stream started without poses (odometry world frame anchored at its first frame); "
            "a request pose would be in another world frame: DELETE the stream to switch to poses",
        )


def check_gap(previous_timestamp: float | None, timestamp: float, min_gap_s: float) -> None:
    """422 `timestamp_gap_too_small` when a frame follows the stream's last accepted frame by less than `min_gap_s`
    (RAFD_MIN_FRAME_GAP_S): no radar scans that fast, and a gap of 1e-300 s makes every speed and flow meaningless."""
    if previous_timestamp is not None and timestamp - previous_timestamp < min_gap_s:
        raise ApiError(
            "timestamp_gap_too_small",
            f"rule min_frame_gap: timestamp {timestamp!r} follows the stream's last accepted frame "
            f"({previous_timestamp!r}) by {timestamp - previous_timestamp:.6g} s, less than the {min_gap_s:g} s a "
            "sensor's frames are at least apart (RAFD_MIN_FRAME_GAP_S)",
        )


def check_motion(
    previous_pose: np.ndarray | None,
    previous_timestamp: float | None,
    pose: np.ndarray,
    timestamp: float,
    max_speed_mps: float,
) -> None:
    """422 `implausible_motion` when the frame's pose (the request's or odometry's) is further from the stream's last
    pose than a road vehicle travels in the time between them (RAFD_MAX_SPEED_MPS): the frame is refused and the
    chain keeps its last pose, instead of every later frame being offset by the jump."""
    if previous_pose is None or previous_timestamp is None or max_speed_mps <= 0:
        return
    distance = float(np.hypot(pose[0] - previous_pose[0], pose[1] - previous_pose[1]))
    elapsed = timestamp - previous_timestamp
    if not distance <= max_speed_mps * elapsed:  # also refuses a non-finite distance
        raise ApiError(
            "implausible_motion",
            f"rule max_speed: the pose moved {distance:.6g} m in {elapsed:.6g} s since the stream's last accepted "
            f"frame, faster than {max_speed_mps:g} m/s (RAFD_MAX_SPEED_MPS); the frame is refused and the stream "
            "keeps its last pose. Check the pose (or, without one, the scans), or DELETE the stream to start over",
        )


def remember(view: np.ndarray, timestamp: float, sweep: Sweep | None) -> OdometryMemory:
    """A frame whose pose needed no odometry (a stream's first, or a request pose): kept raw, prepared only if a
    later frame needs odometry from it."""
    return OdometryMemory(view, timestamp, sweep)


def odometry_pose(
    previous_pose: np.ndarray,
    memory: OdometryMemory,
    view: np.ndarray,
    timestamp: float,
    sweep: Sweep | None,
    resolution: float,
    odometry: Odometry | None = None,
) -> tuple[np.ndarray, OdometryMemory]:
    """[3] world pose of the frame (previous pose o the ego motion since the previous frame) and the stream's
    memory after it. `odometry`: a pairwise registration instead of the stream's tracker."""
    if odometry is not None:
        relative = _pairwise(odometry, memory.view, view, resolution)
        return _composed(previous_pose, relative), OdometryMemory(view, timestamp, sweep)
    tracker_module = _tracker_module()
    tracker: OdometryStream
    if memory.view.shape != view.shape:  # a stream switched between full scans and model-size crops
        relative = _pairwise(tracker_module.estimate_relative_pose, memory.view, view, resolution)
        return _composed(previous_pose, relative), OdometryMemory(view, timestamp, sweep)
    if memory.tracker is not None:
        tracker = memory.tracker.fork()
    else:  # the previous frame was kept raw: start the stream's tracker with it
        tracker = tracker_module.OdometryStream(resolution)
        tracker.add(memory.view, memory.timestamp, _timing(memory.sweep))
    try:
        motion = tracker.add(view, timestamp, _timing(sweep))
    except ValueError as exc:  # timestamps not increasing reach here only if the store let them through
        raise ApiError("odometry_failed", f"odometry could not register the frame: {exc}") from exc
    assert motion is not None  # the tracker holds a previous scan
    return _composed(previous_pose, motion), OdometryMemory(view, timestamp, sweep, tracker)


def _tracker_module() -> ModuleType:
    """rafd.odometry.registration, imported on first use (never at service import)."""
    try:
        from rafd.odometry import registration
    except ImportError as exc:
        raise ApiError(
            "odometry_unavailable", f"this build cannot estimate ego motion ({exc}); send a pose with every frame"
        ) from exc
    return registration


def _timing(sweep: Sweep | None) -> SweepTiming | None:
    if sweep is None:
        return None
    timing: SweepTiming = _tracker_module().SweepTiming.of_native(*sweep)
    return timing


def _pairwise(odometry: Odometry, previous: np.ndarray, current: np.ndarray, resolution: float) -> np.ndarray:
    if previous.shape != current.shape:
        side = min(previous.shape[0], current.shape[0])
        previous, current = centre_crop(previous, side), centre_crop(current, side)
    return np.asarray(odometry(previous, current, resolution), dtype=np.float64)


def _composed(previous_pose: np.ndarray, relative: np.ndarray) -> np.ndarray:
    relative = np.asarray(relative, dtype=np.float64)
    if relative.shape != (3,) or not np.all(np.isfinite(relative)):
        raise ApiError("odometry_failed", f"odometry returned {relative!r}; expected 3 finite numbers")
    return compose_poses(previous_pose, relative)
