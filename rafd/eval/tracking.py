"""The tracking evaluation of `rafd eval --tracking`: the tracker (rafd.tracking) run over each evaluated sequence as a
stream, scored as the field scores trackers and velocity estimates.

- Tracking: HOTA (DetA, AssA), MOTA, IDF1 and ID switches by TrackEval on 2 m centre-distance matching
  (rafd.eval.tracking_metrics), overall, by range band and by weather.
- Velocity: each tracked box matched to a labelled vehicle (Hungarian on centre distance, within 2 m) compares its
  velocity with the true one (rafd.eval.velocity_truth): mean and p90 of |v - v_true| in m/s, for each of the four
  velocity candidates (rafd.tracking.settings.VELOCITY_MODES) and the issue's two baselines: the flow at the
  detection's centre / the pair's interval (every sample, unchecked) and the difference of a vehicle's matched
  detection centres between consecutive scans.
- Identity: the share of vehicles matched in two consecutive scans whose two boxes carry the same track id.
- Does time help detection: the recall at <= 1 false positive per scan (centres within 2 m) of the detections
  alone and of the tracker's answers (confirmed tracks only, with coasting boxes), each at its best input threshold.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Callable, Iterable, Sequence
from dataclasses import replace
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from rafd.detections import answered
from rafd.eval.predict import RANGE_BANDS_M, outside_ignored
from rafd.eval.tracking_inputs import TrackingFrame
from rafd.eval.tracking_metrics import MATCH_DISTANCE_M, FrameTracks, tracking_metrics
from rafd.geometry import rotation_matrix, transform_points
from rafd.protocol import OperatingThreshold
from rafd.tracking import VELOCITY_MODES, FlowField, TrackedBoxes, TrackerSettings, TrackerState, flow_velocity, step
from rafd.tracking.state import SOURCE_NONE

SHIPPED = TrackerSettings()  # the settings the answer uses (docs/tracking.md says how they were chosen)
# "Does time help detection": what the tracker answers in each variant
DETECTION_VARIANTS: dict[str, TrackerSettings | None] = {
    "detections": None,  # every detection above the threshold, no tracker
    "confirmed": replace(SHIPPED, answer_tentative=False),
    "with_coasting": replace(SHIPPED, answer_coasting=True),
    "confirmed_with_coasting": replace(SHIPPED, answer_tentative=False, answer_coasting=True),
}


def sequences_of(frames: Sequence[TrackingFrame]) -> dict[str, list[TrackingFrame]]:
    """TrackingFrames -> {sequence: its frames by frame number}."""
    grouped: dict[str, list[TrackingFrame]] = defaultdict(list)
    for frame in frames:
        grouped[frame.sequence].append(frame)
    return {name: sorted(group, key=lambda f: f.frame) for name, group in sorted(grouped.items())}


def run_tracker(
    frames: Sequence[TrackingFrame], settings: TrackerSettings, score_threshold: OperatingThreshold | float
) -> list[TrackedBoxes]:
    """One sequence's frames (in order) as one stream -> each frame's answer. Coasting boxes that fall in an ignore
    region are dropped like the detections there (neither true nor false)."""
    state = TrackerState.empty()
    answers = []
    for frame in frames:
        kept = answered(frame.detections, score_threshold)
        answer, state = step(
            state, kept[:, :5], frame.pose, frame.timestamp, scores=kept[:, 5], flow=frame.flow, settings=settings
        )
        if len(frame.ignore) and (answer.detection_index < 0).any():
            rows = np.concatenate([answer.boxes, answer.scores[:, None]], 1)
            visible = np.isin(np.arange(len(answer)), _kept_rows(rows, frame.ignore)) | (answer.detection_index >= 0)
            answer = _subset(answer, np.flatnonzero(visible))
        answers.append(answer)
    return answers


def _kept_rows(rows: np.ndarray, ignore: np.ndarray) -> np.ndarray:
    """Indices of the [N, 6] rows outside_ignored keeps."""
    kept = outside_ignored(rows, ignore)
    return np.flatnonzero((rows[:, None, :] == kept[None, :, :]).all(-1).any(1))


def _subset(answer: TrackedBoxes, rows: np.ndarray) -> TrackedBoxes:
    names = [n for n in TrackedBoxes.__dataclass_fields__ if n != "dropped"]
    return replace(answer, **{n: getattr(answer, n)[rows] for n in names})


def match(truth_xy: np.ndarray, found_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """[M, 2], [N, 2] -> (truth rows, found rows) of the one-to-one pairs within MATCH_DISTANCE_M (Hungarian)."""
    if len(truth_xy) == 0 or len(found_xy) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    distance = np.hypot(*(truth_xy[:, None, :2] - found_xy[None, :, :2]).transpose(2, 0, 1))
    rows, columns = linear_sum_assignment(np.where(distance <= MATCH_DISTANCE_M, distance, 1e6))
    keep = distance[rows, columns] <= MATCH_DISTANCE_M
    return rows[keep], columns[keep]


# ---------------------------------------------------------------- per matched box
def matched_records(frames: Sequence[TrackingFrame], answers: Sequence[TrackedBoxes]) -> list[dict[str, Any]]:
    """One record per (labelled vehicle, tracked box) pair: its true and answered velocity, source, range, track
    id, the vehicle's id and the frame's position, for the velocity and identity figures."""
    records = []
    for position, (frame, answer) in enumerate(zip(frames, answers)):
        truth_rows, rows = match(frame.truth[:, :2], answer.boxes[:, :2])
        for t, r in zip(truth_rows, rows):
            records.append(
                {
                    "position": position,
                    "frame": frame.frame,
                    "truth_id": int(frame.truth_ids[t]),
                    "track_id": int(answer.track_id[r]),
                    "truth_velocity": frame.truth_velocity[t],
                    "velocity": answer.velocity[r],
                    "source": int(answer.velocity_source[r]),
                    "range": float(np.hypot(*frame.truth[t, :2])),
                }
            )
    return records


MOVING_SPEED = 0.5  # m/s: a labelled vehicle moving faster than this counts as moving (parked ones are at 0)


def velocity_summary(records: Iterable[dict[str, Any]]) -> dict[str, Any]:
    """Velocity errors (m/s) of matched boxes with a known true velocity: over the boxes whose velocity has a source
    (mean, p90) and over all of them (a box without one answers its prior, 0 m/s), with the coverage; and over all of
    them split into moving and parked vehicles (a parked majority rewards answering 0 m/s: read both)."""
    known = [r for r in records if np.isfinite(r["truth_velocity"]).all()]
    errors = np.array([np.hypot(*(r["velocity"] - r["truth_velocity"])) for r in known])
    sourced = np.array([r["source"] != SOURCE_NONE for r in known], bool)
    speeds = np.array([np.hypot(*r["truth_velocity"]) for r in known])
    moving = speeds >= MOVING_SPEED
    return {
        "matched": len(known),
        "with_velocity": int(sourced.sum()),
        "coverage": 100.0 * float(sourced.mean()) if len(known) else math.nan,
        "mean": _mean(errors[sourced]),
        "p90": _p90(errors[sourced]),
        "mean_all": _mean(errors),
        "p90_all": _p90(errors),
        "moving": int(moving.sum()),
        "mean_moving": _mean(errors[moving]),
        "p90_moving": _p90(errors[moving]),
        "mean_parked": _mean(errors[~moving]),
        "mean_true_speed": _mean(speeds),
    }


def _mean(values: np.ndarray) -> float:
    return float(np.mean(values)) if len(values) else math.nan


def _p90(values: np.ndarray) -> float:
    return float(np.percentile(values, 90)) if len(values) else math.nan


def identity_kept(records: Sequence[dict[str, Any]], numbers: Sequence[int]) -> tuple[int, int]:
    """One stream's matched records and its frame numbers (by position) -> (pairs, kept): the vehicles matched in
    two consecutive scans, and those whose two boxes carry the same track id."""
    by_frame = {(r["position"], r["truth_id"]): r["track_id"] for r in records}
    pairs = [
        (by_frame[(p - 1, i)], track)
        for (p, i), track in by_frame.items()
        if p > 0 and numbers[p - 1] == numbers[p] - 1 and (p - 1, i) in by_frame
    ]
    return len(pairs), sum(1 for before, now in pairs if before == now)


# ---------------------------------------------------------------- the two baselines
def baseline_records(
    frames: Sequence[TrackingFrame], score_threshold: OperatingThreshold | float
) -> dict[str, list[dict[str, Any]]]:
    """Per matched detection: the flow at its centre / the interval, unchecked (any validity, no saturation test),
    and the difference of its centre and the previous scan's detection matched to the same vehicle."""
    out: dict[str, list[dict[str, Any]]] = {"flow_centre_unchecked": [], "centre_differencing": []}
    previous: dict[int, np.ndarray] = {}  # vehicle id -> world centre of its matched detection in the last scan
    previous_frame: TrackingFrame | None = None
    for frame in frames:
        found = answered(frame.detections, score_threshold)
        truth_rows, rows = match(frame.truth[:, :2], found[:, :2])
        flow = _unchecked_flow(frame.flow, found[rows, :5])
        world = transform_points(frame.pose, found[rows, :2]) if len(rows) else np.zeros((0, 2))
        consecutive = previous_frame is not None and frame.frame == previous_frame.frame + 1
        current: dict[int, np.ndarray] = {}
        for k, (t, _r) in enumerate(zip(truth_rows, rows)):
            vehicle = int(frame.truth_ids[t])
            record = {"truth_velocity": frame.truth_velocity[t], "range": float(np.hypot(*frame.truth[t, :2]))}
            has_flow = bool(np.isfinite(flow[k]).all())
            out["flow_centre_unchecked"].append(
                record | {"velocity": flow[k] if has_flow else np.zeros(2), "source": 1 if has_flow else SOURCE_NONE}
            )
            if consecutive and previous_frame is not None and vehicle in previous:
                dt = frame.timestamp - previous_frame.timestamp
                moved = rotation_matrix(-frame.pose[2]) @ ((world[k] - previous[vehicle]) / dt)
                out["centre_differencing"].append(record | {"velocity": moved, "source": 2})
            else:
                out["centre_differencing"].append(record | {"velocity": np.zeros(2), "source": SOURCE_NONE})
            current[vehicle] = world[k]
        previous, previous_frame = current, frame
    return out


def _unchecked_flow(fields: tuple[FlowField, ...] | None, boxes: np.ndarray) -> np.ndarray:
    """[N, 2] the flow at each box centre / the interval from the best tile, with no validity or reach check."""
    measured = flow_velocity(fields, boxes, "centre", std_floor=1.0, min_validity=0.0, reach_fraction=1e9)
    return measured.velocity


# ---------------------------------------------------------------- the report
def _scores_of(
    streams: dict[str, list[TrackingFrame]], answers: dict[str, list[TrackedBoxes]], keep: Callable | None = None
) -> dict[str, Any]:
    """TrackEval's figures of the answers, with `keep(frame, xy) -> bool mask` choosing the boxes scored (a band)."""
    sequences = {}
    for name, frames in streams.items():
        rows = []
        for frame, answer in zip(frames, answers[name]):
            truth_mask = keep(frame.truth[:, :2]) if keep else np.ones(len(frame.truth), bool)
            track_mask = keep(answer.boxes[:, :2]) if keep else np.ones(len(answer), bool)
            rows.append(
                FrameTracks(
                    frame.truth[truth_mask, :2],
                    frame.truth_ids[truth_mask],
                    answer.boxes[track_mask, :2],
                    answer.track_id[track_mask],
                )
            )
        sequences[name] = rows
    return tracking_metrics(sequences)


def _band(lo: float, hi: float) -> Callable[[np.ndarray], np.ndarray]:
    return lambda xy: (np.hypot(xy[:, 0], xy[:, 1]) >= lo) & (np.hypot(xy[:, 0], xy[:, 1]) < hi)


def _band_name(lo: float, hi: float) -> str:
    return f"{lo:g}-{hi:g} m" if math.isfinite(hi) else f">= {lo:g} m"


def evaluate_tracking(
    frames: Sequence[TrackingFrame],
    score_threshold: OperatingThreshold | float,
    settings: TrackerSettings = SHIPPED,
    velocity_truth: str = "",
    detection_study: bool = True,
) -> dict[str, Any]:
    """TrackingFrames of any number of sequences and the operating threshold -> the tracking report (see the module
    docstring): "tracking" (overall, by range, by condition) and "velocity" for `settings`, "candidates" side by side,
    "baselines", "identity_kept" and (detection_study) "time_helps_detection"."""
    streams = sequences_of(frames)
    report: dict[str, Any] = {
        "score_threshold": _threshold_json(score_threshold),
        "velocity_truth": velocity_truth,
        "settings": settings.velocity,
        "sequences": len(streams),
        "frames": len(frames),
    }
    candidates = {}
    for mode in VELOCITY_MODES:
        chosen = replace(settings, velocity=mode)
        answers = {name: run_tracker(group, chosen, score_threshold) for name, group in streams.items()}
        records = [r for name, group in streams.items() for r in matched_records(group, answers[name])]
        candidates[mode] = {
            "velocity": velocity_summary(records),
            "identity_kept": identity_kept_by_stream(streams, answers),
            "tracking": _scores_of(streams, answers),
        }
        if mode == settings.velocity:
            report["tracking"] = candidates[mode]["tracking"]
            report["velocity"] = candidates[mode]["velocity"]
            report["identity_kept"] = candidates[mode]["identity_kept"]
            report["by_range"] = {
                _band_name(lo, hi): {
                    "tracking": _scores_of(streams, answers, _band(lo, hi)),
                    "velocity": velocity_summary(r for r in records if lo <= r["range"] < hi),
                }
                for lo, hi in zip(RANGE_BANDS_M[:-1], RANGE_BANDS_M[1:])
            }
            conditions = sorted({f.condition or "unknown" for f in frames})
            report["by_condition"] = {
                condition: {
                    "tracking": _scores_of(
                        {n: g for n, g in streams.items() if (g[0].condition or "unknown") == condition},
                        answers,
                    ),
                    "velocity": velocity_summary(
                        r
                        for name, group in streams.items()
                        if (group[0].condition or "unknown") == condition
                        for r in matched_records(group, answers[name])
                    ),
                }
                for condition in conditions
            }
    report["candidates"] = candidates
    baselines: dict[str, list[dict[str, Any]]] = {"flow_centre_unchecked": [], "centre_differencing": []}
    for group in streams.values():
        for name, records in baseline_records(group, score_threshold).items():
            baselines[name] += records
    report["baselines"] = {name: velocity_summary(records) for name, records in baselines.items()}
    if detection_study:
        report["time_helps_detection"] = time_helps_detection(streams, score_threshold)
    return report


def identity_kept_by_stream(
    streams: dict[str, list[TrackingFrame]], answers: dict[str, list[TrackedBoxes]]
) -> dict[str, Any]:
    """identity_kept pooled over the streams."""
    pairs = kept = 0
    for name, group in streams.items():
        counted = identity_kept(matched_records(group, answers[name]), [f.frame for f in group])
        pairs, kept = pairs + counted[0], kept + counted[1]
    return {"pairs": pairs, "kept": kept, "percent": 100.0 * kept / pairs if pairs else math.nan}


# ---------------------------------------------------------------- does time help detection
def time_helps_detection(
    streams: dict[str, list[TrackingFrame]],
    score_threshold: OperatingThreshold | float,
    budget: float = 1.0,
    steps: int = 24,
    resamples: int = 1000,
    seed: int = 0,
) -> dict[str, Any]:
    """The recall (centres within 2 m) at <= `budget` false positives per scan of each DETECTION_VARIANTS entry,
    each at its best input score threshold among `steps` candidates (the detections' own thresholds at 0.25 to 8
    false positives per scan, and the operating threshold), and each variant's difference from the detections alone
    with a 95% bootstrap interval over streams (the threshold chosen again in every resample)."""
    frames = [f for group in streams.values() for f in group]
    sweep = sorted(set(_thresholds_at(frames, np.geomspace(0.25, 8.0, steps - 1))))
    thresholds: list[OperatingThreshold | float] = [*sweep, score_threshold]  # the operating one last
    counts = {name: _counts(streams, settings, thresholds) for name, settings in DETECTION_VARIANTS.items()}
    scans = np.array([len(group) for group in streams.values()], np.float64)  # [S]
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, len(scans), (resamples, len(scans)))  # [R, S] streams drawn with replacement
    base = _best_recall(counts["detections"][picks].sum(1), scans[picks].sum(1), budget)  # [R]
    result: dict[str, Any] = {}
    for name, table in counts.items():
        pooled = table.sum(0)  # [T, 3] found, labelled, false
        recall = 100.0 * pooled[:, 0] / np.maximum(pooled[:, 1], 1)
        per_scan = pooled[:, 2] / max(scans.sum(), 1)
        within = np.flatnonzero(per_scan <= budget)
        best = int(within[np.argmax(recall[within])]) if len(within) else -1
        operating = len(thresholds) - 1
        result[name] = {
            "at_budget": {
                "recall": float(recall[best]) if best >= 0 else 0.0,
                "fp_per_frame": float(per_scan[best]) if best >= 0 else math.nan,
                "threshold": _threshold_json(thresholds[best]) if best >= 0 else math.nan,
            },
            "at_operating_threshold": {
                "recall": float(recall[operating]),
                "fp_per_frame": float(per_scan[operating]),
                "threshold": _threshold_json(score_threshold),
            },
        }
        if name != "detections":
            difference = _best_recall(table[picks].sum(1), scans[picks].sum(1), budget) - base
            result[name]["difference_from_detections"] = {
                "points": result[name]["at_budget"]["recall"] - result["detections"]["at_budget"]["recall"],
                "interval95": [float(np.percentile(difference, 2.5)), float(np.percentile(difference, 97.5))],
            }
    result["budget_fp_per_frame"] = budget
    result["vehicles"] = int(sum(len(f.truth) for f in frames))
    result["frames"] = len(frames)
    result["streams"] = len(streams)
    return result


def _counts(
    streams: dict[str, list[TrackingFrame]],
    settings: TrackerSettings | None,
    thresholds: Sequence[OperatingThreshold | float],
) -> np.ndarray:
    """-> [S, T, 3] per stream and input threshold: vehicles found, vehicles labelled, false boxes answered."""
    table = np.zeros((len(streams), len(thresholds), 3))
    for s, group in enumerate(streams.values()):
        for t, threshold in enumerate(thresholds):
            answers = (
                [answered(f.detections, threshold)[:, :2] for f in group]
                if settings is None
                else [a.boxes[:, :2] for a in run_tracker(group, settings, threshold)]
            )
            for frame, xy in zip(group, answers):
                truth_rows, _ = match(frame.truth[:, :2], xy)
                table[s, t] += (len(truth_rows), len(frame.truth), len(xy) - len(truth_rows))
    return table


def _threshold_json(threshold: OperatingThreshold | float) -> float | str:
    """A threshold in a report: the number, or its description when it differs by range."""
    if isinstance(threshold, OperatingThreshold):
        return threshold.near if threshold.far is None else str(threshold)
    return float(threshold)


def _best_recall(counts: np.ndarray, scans: np.ndarray, budget: float) -> np.ndarray:
    """[R, T, 3] resampled counts and [R] scans -> [R] the best recall (%) within the budget (0 where none is)."""
    recall = 100.0 * counts[..., 0] / np.maximum(counts[..., 1], 1)  # [R, T]
    within = counts[..., 2] / np.maximum(scans[:, None], 1) <= budget
    return np.where(within, recall, 0.0).max(1)


def _thresholds_at(frames: Sequence[TrackingFrame], budgets: np.ndarray) -> list[float]:
    """The detections' score thresholds that leave about `budgets` false positives per scan (unmatched detections
    counted at each score, matching each scan once at the lowest score)."""
    false_scores = []
    for frame in frames:
        _, rows = match(frame.truth[:, :2], frame.detections[:, :2])
        unmatched = np.setdiff1d(np.arange(len(frame.detections)), rows)
        false_scores.append(frame.detections[unmatched, 5])
    scores = np.sort(np.concatenate(false_scores + [np.zeros(0)]))[::-1]
    picks = []
    for budget in budgets:
        index = int(budget * len(frames))
        if index < len(scores):
            picks.append(float(np.nextafter(scores[index], np.inf)))
    return picks
