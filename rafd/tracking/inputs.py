"""What a scan hands the tracker, checked: a frame that would poison every track (a non-finite pose or time, a time
not after the last scan's) is refused whole, leaving the state as it was; a box that would poison its own track is
dropped with a reason, and the rest are tracked."""

from __future__ import annotations

import math

import numpy as np

MAX_RANGE_M = 10_000.0  # a detection farther from the radar than this is a broken input, not a radar return


class FrameRefused(ValueError):
    """The scan cannot be tracked (the message says why); the state passed in is unchanged and still valid."""


def checked_pose(pose: object) -> np.ndarray:
    """-> the world pose [3] float64 (x, y, yaw); FrameRefused unless it is 3 finite numbers."""
    try:
        array = np.asarray(pose, np.float64).reshape(-1)
    except (TypeError, ValueError) as error:
        raise FrameRefused(f"pose is not 3 numbers: {error}") from error
    if array.shape != (3,) or not np.isfinite(array).all():
        raise FrameRefused(f"pose must be 3 finite numbers (x, y, yaw), got {array.tolist()}")
    return array


def checked_time(timestamp: object, last: float | None) -> float:
    """-> the scan time in seconds; FrameRefused unless finite and after the last scan stepped (a replayed or
    reordered frame must not move the tracks)."""
    try:
        value = float(timestamp)  # type: ignore[arg-type]
    except (TypeError, ValueError) as error:
        raise FrameRefused(f"timestamp is not a number: {timestamp!r}") from error
    if not math.isfinite(value):
        raise FrameRefused(f"timestamp must be finite, got {value}")
    if last is not None and value <= last:
        raise FrameRefused(f"timestamp {value!r} is not after the last scan tracked ({last!r})")
    return value


def checked_boxes(
    boxes: object, scores: object | None, labels: object | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[tuple[int, str]]]:
    """Boxes [N, 5] (x, y, width, length, yaw), scores [N] (None: 1), labels [N] (None: 0) -> (the kept boxes [M, 5],
    scores [M], labels [M], their input indices [M], [(input index, reason)] of the dropped). FrameRefused when
    the arrays do not fit together."""
    try:
        array = np.asarray(boxes, np.float64).reshape(-1, 5)
        count = len(array)
        score = np.ones(count) if scores is None else np.asarray(scores, np.float64).reshape(-1)
        label = np.zeros(count, np.int64) if labels is None else np.asarray(labels).reshape(-1)
    except (TypeError, ValueError) as error:
        raise FrameRefused(f"boxes must be [N, 5] numbers with [N] scores and labels: {error}") from error
    if len(score) != count or len(label) != count:
        raise FrameRefused(f"{count} boxes but {len(score)} scores and {len(label)} labels")
    if count and not np.issubdtype(label.dtype, np.integer):
        finite_labels = np.isfinite(label.astype(np.float64))
        label = np.where(finite_labels, label.astype(np.float64), -1).astype(np.int64)
    label = label.astype(np.int64)
    finite = np.asarray(np.isfinite(array).all(1))
    checks: tuple[tuple[str, np.ndarray], ...] = (
        ("non-finite box", finite),
        ("non-positive size", (array[:, 2] > 0) & (array[:, 3] > 0)),
        (f"farther than {MAX_RANGE_M:g} m", np.abs(array[:, :2]).max(1, initial=0.0) <= MAX_RANGE_M),
        ("non-finite score", np.isfinite(score)),
        ("negative class", label >= 0),
    )
    good = np.logical_and.reduce([passed for _, passed in checks]) if count else np.zeros(0, bool)
    kept = np.flatnonzero(good)
    dropped: list[tuple[int, str]] = []
    for index in np.flatnonzero(~good):  # the first check each failed (a NaN box fails the later ones too)
        dropped.append((int(index), next(reason for reason, passed in checks if not passed[index])))
    return array[kept], score[kept], label[kept], kept, dropped
