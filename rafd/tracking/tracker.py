"""step(state, boxes, pose, timestamp, ...) -> (TrackedBoxes, new state): one scan of one stream through the tracker.

Every kept detection becomes a track's box: it continues the track whose predicted centre it is matched with
(rafd.tracking.matching, gated) or begins a new one. Tracks live in the world frame given by the scans' poses, so
the ego's own motion is removed from positions and velocities alike; answers are turned back into the scan's ego
axes. Life cycle: tentative until `confirm_hits` detections, then confirmed; a confirmed track missed by the
detector coasts on its prediction for up to `max_coast_frames` scans (a tentative one `tentative_coast_frames`,
and only a confirmed one's predicted box is ever answered).
The state passed in is never modified (rafd.tracking.state).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from rafd.geometry import wrap_angle
from rafd.tracking import motion
from rafd.tracking.flow import FlowField, FlowVelocity, flow_velocity
from rafd.tracking.inputs import checked_boxes, checked_pose, checked_time
from rafd.tracking.matching import assign, gated_costs
from rafd.tracking.settings import TrackerSettings
from rafd.tracking.state import (
    COASTING,
    CONFIRMED,
    SOURCE_FLOW,
    SOURCE_NONE,
    SOURCE_TRACK,
    STATUS_NAMES,
    TENTATIVE,
    VELOCITY_SOURCES,
    TrackerState,
    concatenate,
    rows_of,
)

DEFAULT_SETTINGS = TrackerSettings()


@dataclass(frozen=True)
class TrackedBoxes:
    """The answered boxes of one scan, row k = one box (the kept detections in input order, then the coasting
    tracks' predicted boxes when answered). Velocities are ground velocities (ego motion removed) in m/s in the
    scan's ego axes (x right, y forward); velocity_covariance is their 2x2 covariance in (m/s)^2."""

    boxes: np.ndarray  # [M, 5] (x, y, width, length, yaw) ego frame
    scores: np.ndarray  # [M] (a coasting box: its last detection's score decayed per missed scan)
    labels: np.ndarray  # [M] int64 class index
    detection_index: np.ndarray  # [M] int64 row of the input boxes; -1 for a coasting track's predicted box
    track_id: np.ndarray  # [M] int64
    age: np.ndarray  # [M] int64 scans since the track began (1 = this one)
    hits: np.ndarray  # [M] int64 scans with a detection
    status: np.ndarray  # [M] int8, STATUS_NAMES
    velocity: np.ndarray  # [M, 2] m/s
    velocity_covariance: np.ndarray  # [M, 2, 2] (m/s)^2
    velocity_source: np.ndarray  # [M] int8, VELOCITY_SOURCES
    dropped: tuple[tuple[int, str], ...] = ()  # (input row, reason) of the detections not tracked

    def __len__(self) -> int:
        return len(self.track_id)

    def records(self) -> list[dict[str, Any]]:
        """One plain dict per box (JSON-ready numbers; velocity_std = the per-axis standard deviations)."""
        return [
            {
                "box": [float(v) for v in self.boxes[k]],
                "score": float(self.scores[k]),
                "label": int(self.labels[k]),
                "detection_index": int(self.detection_index[k]),
                "track_id": int(self.track_id[k]),
                "age": int(self.age[k]),
                "hits": int(self.hits[k]),
                "status": STATUS_NAMES[int(self.status[k])],
                "velocity": {"x": float(self.velocity[k, 0]), "y": float(self.velocity[k, 1])},
                "velocity_covariance": self.velocity_covariance[k].tolist(),
                "velocity_source": VELOCITY_SOURCES[int(self.velocity_source[k])],
            }
            for k in range(len(self))
        ]


def step(
    state: TrackerState,
    boxes: np.ndarray,
    pose: np.ndarray,
    timestamp: float,
    *,
    scores: np.ndarray | None = None,
    labels: np.ndarray | None = None,
    flow: FlowField | Sequence[FlowField] | None = None,
    settings: TrackerSettings = DEFAULT_SETTINGS,
) -> tuple[TrackedBoxes, TrackerState]:
    """One scan: its detections boxes [N, 5] (ego frame), world pose [3] (float64), time (seconds), optional scores
    [N], class labels [N] and the newest pair's flow (one field or the tiles of a mosaic) -> (its tracked boxes, the
    next state). Raises FrameRefused (the state untouched) for a non-finite pose or time, or a time not after the
    last scan's; non-finite boxes are dropped with a reason (TrackedBoxes.dropped)."""
    pose = checked_pose(pose)
    timestamp = checked_time(timestamp, state.timestamp)
    detections, det_scores, det_labels, det_index, dropped = checked_boxes(boxes, scores, labels)
    rotation = _rotation(pose[2])  # [2, 2] ego -> world
    world_xy = detections[:, :2] @ rotation.T + pose[:2]  # [D, 2]
    measured = _flow_measurement(flow, detections, rotation, settings)

    dt = 0.0 if state.timestamp is None else timestamp - state.timestamp
    tracks = state if dt <= settings.max_gap_s else state.take(np.zeros(len(state), bool))  # a long gap ends all
    mean, covariance = motion.predict(tracks.mean, tracks.covariance, dt, settings.acceleration_std)
    rows, columns = _associate(tracks, mean, covariance, world_xy, det_labels, settings)

    matched = _continue(tracks, mean, covariance, rows, columns, world_xy, measured, settings)
    unmatched = _others(len(detections), columns)
    born = _begin(unmatched, world_xy, measured, settings)
    missed = _miss(tracks, mean, covariance, _others(len(tracks), rows), settings)
    # the detections' own rows: matched first, then born; box, score, label from this scan's detection
    order = np.concatenate([columns, unmatched])
    seen = concatenate([matched, born])
    seen.update(
        size=detections[order, 2:4],
        yaw=detections[order, 4] + pose[2],
        score=det_scores[order],
        label=det_labels[order],
    )
    seen, order, missed, capped = _cap(seen, order, len(columns), missed, det_scores, settings.max_tracks)
    dropped += [(int(det_index[i]), "track cap") for i in capped]
    first_new = len(columns)
    new_ids = state.next_id + np.arange(len(order) - first_new, dtype=np.int64)  # ids only ever count up
    seen["ids"] = np.concatenate([seen["ids"][:first_new], new_ids])
    next_state = TrackerState(
        **concatenate([seen, missed]),
        next_id=int(state.next_id + len(new_ids)),
        timestamp=timestamp,
        scans=state.scans + 1,
    )
    answer = _answer(next_state, detections[order], det_index[order], measured, order, pose, settings)
    return replace(answer, dropped=tuple(sorted(dropped))) if dropped else answer, next_state


def _rotation(yaw: float) -> np.ndarray:
    """-> [2, 2] the counter-clockwise rotation by yaw (ego -> world axes)."""
    cos, sin = np.cos(yaw), np.sin(yaw)
    return np.array([[cos, -sin], [sin, cos]])


def _others(count: int, taken: np.ndarray) -> np.ndarray:
    """-> the indices of range(count) not in `taken`, ascending."""
    free = np.ones(count, bool)
    free[taken] = False
    return np.flatnonzero(free)


# ---------------------------------------------------------------- the flow as a measurement
@dataclass(frozen=True)
class _Measured:
    """The flow's velocity per detection in the WORLD frame (NaN where unusable) and its per-axis variance."""

    velocity: np.ndarray  # [D, 2]
    variance: np.ndarray  # [D]
    ego: FlowVelocity | None


def _flow_measurement(
    flow: FlowField | Sequence[FlowField] | None, detections: np.ndarray, rotation: np.ndarray, s: TrackerSettings
) -> _Measured:
    count = len(detections)
    if not s.uses_flow or flow is None:
        return _Measured(np.full((count, 2), np.nan), np.full(count, np.nan), None)
    how = "centre" if s.velocity == "flow_centre" else "box"
    ego = flow_velocity(flow, detections, how, s.flow_std_floor, s.flow_min_validity, s.flow_reach_fraction)
    return _Measured(ego.velocity @ rotation.T, ego.variance, ego)  # an isotropic variance turns unchanged


# ---------------------------------------------------------------- association
def _associate(
    tracks: TrackerState,
    mean: np.ndarray,
    covariance: np.ndarray,
    world_xy: np.ndarray,
    labels: np.ndarray,
    s: TrackerSettings,
) -> tuple[np.ndarray, np.ndarray]:
    """-> (track rows [M], detection columns [M]) matched."""
    if len(tracks) == 0 or len(world_xy) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    distance_sq = motion.mahalanobis_squared(mean[:, :2], covariance[:, :2, :2], world_xy, s.position_std_m**2)
    gates = np.full(len(tracks), s.gate_m)
    if s.class_gates_m:
        gates = np.array([s.gate_for(label) for label in tracks.label])
    same_class = tracks.label[:, None] == labels[None, :]  # [T, D]
    costs = gated_costs(mean[:, :2], world_xy, distance_sq, gates, s.gate_sigmas, same_class)
    return assign(costs, s.matching)


# ---------------------------------------------------------------- the three kinds of rows of the next state
def _continue(
    tracks: TrackerState,
    mean: np.ndarray,
    covariance: np.ndarray,
    rows: np.ndarray,
    columns: np.ndarray,
    world_xy: np.ndarray,
    measured: _Measured,
    s: TrackerSettings,
) -> dict[str, np.ndarray]:
    """Matched tracks updated with their detection's position (and in filter_flow, its flow velocity)."""
    count = len(rows)
    noise = s.position_std_m**2 * _identities(count)
    new_mean, new_cov = motion.update(mean[rows], covariance[rows], world_xy[columns], noise, slice(0, 2))
    if s.velocity == "filter_flow":
        has_flow = np.isfinite(measured.velocity[columns, 0])
        if has_flow.any():
            flow_noise = measured.variance[columns][has_flow, None, None] * np.eye(2)  # [F, 2, 2]
            updated = motion.update(
                new_mean[has_flow], new_cov[has_flow], measured.velocity[columns][has_flow], flow_noise, slice(2, 4)
            )
            new_mean, new_cov = new_mean.copy(), new_cov.copy()
            new_mean[has_flow], new_cov[has_flow] = updated
    return {
        "ids": tracks.ids[rows],
        "mean": new_mean,
        "covariance": new_cov,
        "age": tracks.age[rows] + 1,
        "hits": tracks.hits[rows] + 1,
        "misses": np.zeros(count, np.int64),
        "evidence": np.full(count, SOURCE_TRACK, np.int8),  # two positions or more
    }


def _identities(count: int) -> np.ndarray:
    """-> [N, 2, 2] identity matrices."""
    eye = np.zeros((count, 2, 2))
    eye[:, 0, 0] = eye[:, 1, 1] = 1.0
    return eye


def _begin(columns: np.ndarray, world_xy: np.ndarray, measured: _Measured, s: TrackerSettings) -> dict[str, np.ndarray]:
    """New tracks at unmatched detections: at rest with the speed prior, or (filter_flow) at the flow's velocity."""
    count = len(columns)
    velocity = np.zeros((count, 2))
    velocity_var = s.initial_speed_std**2 * _identities(count)
    evidence = np.full(count, SOURCE_NONE, np.int8)
    if s.velocity == "filter_flow" and count:
        has_flow = np.isfinite(measured.velocity[columns, 0])
        velocity[has_flow] = measured.velocity[columns][has_flow]
        velocity_var[has_flow] = measured.variance[columns][has_flow, None, None] * np.eye(2)
        evidence[has_flow] = SOURCE_FLOW
    return {
        "ids": np.zeros(count, np.int64),  # given after the cap (rafd.tracking.tracker.step)
        "mean": np.concatenate([world_xy[columns], velocity], 1).reshape(count, 4),
        "covariance": motion.initial_covariance(count, s.position_std_m, velocity_var),
        "age": np.ones(count, np.int64),
        "hits": np.ones(count, np.int64),
        "misses": np.zeros(count, np.int64),
        "evidence": evidence,
    }


def _miss(
    tracks: TrackerState, mean: np.ndarray, covariance: np.ndarray, rows: np.ndarray, s: TrackerSettings
) -> dict[str, np.ndarray]:
    """Tracks without a detection coast on their prediction: confirmed ones up to max_coast_frames scans, tentative
    ones up to tentative_coast_frames; the rest end."""
    misses = tracks.misses[rows] + 1
    limit = np.where(tracks.hits[rows] >= s.confirm_hits, s.max_coast_frames, s.tentative_coast_frames)
    keep = rows[misses <= limit]
    finite = np.isfinite(mean[keep]).all(1) & np.isfinite(covariance[keep]).all((1, 2))
    keep = keep[finite]  # defensive: a track that could not be predicted ends rather than poisons the state
    rows_kept = rows_of(tracks)
    kept = {name: values[keep] for name, values in rows_kept.items()}
    kept.update(mean=mean[keep], covariance=covariance[keep], age=tracks.age[keep] + 1, misses=tracks.misses[keep] + 1)
    return kept


def _cap(
    seen: dict[str, np.ndarray],
    order: np.ndarray,
    matched: int,
    missed: dict[str, np.ndarray],
    scores: np.ndarray,
    cap: int,
) -> tuple[dict[str, np.ndarray], np.ndarray, dict[str, np.ndarray], np.ndarray]:
    """Bound the live tracks at `cap`: this scan's detections come first (the `matched` continued ones, then the new
    ones by score: the lowest-scoring new ones are not tracked if they alone exceed it), then the coasting tracks
    (fewest misses, then most hits). -> (seen, order, missed, the detections not tracked)."""
    capped = np.zeros(0, np.int64)
    if len(order) > cap:
        born = np.arange(matched, len(order))
        ranked = born[np.argsort(-scores[order[born]], kind="stable")]
        keep = np.sort(np.concatenate([np.arange(matched), ranked[: cap - matched]]))
        capped = order[np.setdiff1d(born, keep)]
        seen = {name: values[keep] for name, values in seen.items()}
        order = order[keep]
    room = cap - len(order)
    if len(missed["ids"]) > room:
        ranked = np.lexsort((-missed["hits"], missed["misses"]))  # fewest misses first, then most hits
        keep = np.sort(ranked[:room])
        missed = {name: values[keep] for name, values in missed.items()}
    return seen, order, missed, capped


# ---------------------------------------------------------------- the answer
def _answer(
    state: TrackerState,
    detected: np.ndarray,
    det_index: np.ndarray,
    measured: _Measured,
    order: np.ndarray,
    pose: np.ndarray,
    s: TrackerSettings,
) -> TrackedBoxes:
    """The next state's first rows are this scan's detections: their boxes detected [S, 5] as given, their input
    rows det_index [S] and columns `order` [S] among the kept detections; the rest coast. -> the answered boxes in
    the scan's ego frame."""
    seen = len(detected)
    rotation = _rotation(pose[2])  # ego -> world
    status = np.where(state.hits >= s.confirm_hits, CONFIRMED, TENTATIVE).astype(np.int8)
    status[seen:] = COASTING
    answered = np.arange(seen)
    if not s.answer_tentative:
        answered = answered[status[:seen] != TENTATIVE]
    answered = answered[np.argsort(det_index[answered], kind="stable")]  # the input's order
    if s.answer_coasting:
        coasting = np.arange(seen, len(state))
        shown = (state.hits[coasting] >= s.confirm_hits) & (state.misses[coasting] <= s.answer_coast_frames)
        answered = np.concatenate([answered, coasting[shown]])
    velocity = state.mean[answered, 2:].copy()  # [M, 2] world
    covariance = state.covariance[answered, 2:, 2:].copy()  # [M, 2, 2]
    source = state.evidence[answered].copy()
    if s.velocity in ("flow_centre", "flow_box"):  # the candidate answers the flow itself for detected boxes
        rows = answered < seen
        columns = order[answered[rows]]
        has_flow = np.isfinite(measured.velocity[columns, 0])
        velocity[rows] = np.where(has_flow[:, None], measured.velocity[columns], 0.0)
        prior = s.initial_speed_std**2
        variance = np.where(has_flow, measured.variance[columns], prior)
        covariance[rows] = variance[:, None, None] * np.eye(2)
        source[rows] = np.where(has_flow, SOURCE_FLOW, SOURCE_NONE)
    if s.moving_prior is not None:  # parked or moving: the mixture's mean and covariance
        filtered = source != SOURCE_NONE
        if s.velocity in ("flow_centre", "flow_box"):
            filtered &= answered >= seen  # the flow candidates answer the flow itself for detected boxes
        if filtered.any():
            v, p = velocity[filtered], covariance[filtered]
            moving = motion.moving_probability(v, p, s.initial_speed_std, s.moving_prior)[:, None]  # [F, 1]
            velocity[filtered] = moving * v
            spread = v[:, :, None] * v[:, None, :]  # [F, 2, 2] v v'
            covariance[filtered] = moving[:, :, None] * p + (moving * (1 - moving))[:, :, None] * spread
    # world -> ego axes: v_ego = R^T v_world (rows: v @ R), covariance R^T P R
    ego_velocity = velocity @ rotation
    ego_covariance = rotation.T @ covariance @ rotation
    ego_xy = (state.mean[answered, :2] - pose[:2]) @ rotation
    boxes = np.concatenate(
        [ego_xy, state.size[answered], wrap_angle(state.yaw[answered] - pose[2])[:, None]], 1
    ).reshape(-1, 5)
    detected_rows = answered < seen
    boxes[detected_rows] = detected[answered[detected_rows]]  # a detected box is answered as the detector drew it
    misses = state.misses[answered]
    index = np.full(len(answered), -1, np.int64)
    index[detected_rows] = det_index[answered[detected_rows]]
    return TrackedBoxes(
        boxes=boxes,
        scores=state.score[answered] * s.coast_score_decay**misses,
        labels=state.label[answered],
        detection_index=index,
        track_id=state.ids[answered],
        age=state.age[answered],
        hits=state.hits[answered],
        status=status[answered],
        velocity=ego_velocity,
        velocity_covariance=ego_covariance,
        velocity_source=source,
    )
