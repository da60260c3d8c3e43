"""Is model B better than model A on the same frames? A paired bootstrap over drives (torch-free).

Frames of one drive are strongly correlated (the same scene, seconds apart), so the unit of resampling is the drive:
each resample draws as many drives as were scored, with replacement, and weighs every frame of a drive by the number
of times that drive was drawn. Both models are scored on the same resample, and every metric is recomputed from the
detections' fates at full weight (rafd.eval.metrics.ranked_outcomes; a detection's fate depends on its own frame
only, so
resampling frames never changes it). With weight 1 everywhere the figures are exactly rafd.eval.predict.summarise's.

Detections travel between rafd-eval (`--detections FILE.npz`) and this module in a plain npz (no pickle):
sequence name and frame number per frame, and the frames' predictions and ground truths concatenated with offsets.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rafd.eval.metrics import ap_from_counts, last_within_fp_budget, match_centres, ranked_counts, ranked_outcomes
from rafd.protocol import CENTRE_DISTANCE_M, IOU_THRESHOLDS

METRICS = tuple(f"mAP@{t:g}" for t in IOU_THRESHOLDS) + ("centre_AP", "recall_at_1fp")


@dataclass(frozen=True)
class FrameDetections:
    sequence: str
    frame: int
    predictions: np.ndarray  # [N, 6] (x, y, width, length, yaw, score)
    ground_truth: np.ndarray  # [M, 5]


def save_detections(path: Path, results: Sequence[Any]) -> None:
    """Frames with .sequence, .frame, .predictions, .ground_truth (e.g. rafd.eval.predict.FrameResult) -> npz."""
    predictions = [np.asarray(r.predictions, np.float64).reshape(-1, 6) for r in results]
    truths = [np.asarray(r.ground_truth, np.float64).reshape(-1, 5) for r in results]
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as file:  # np.savez would append .npz to a name without it
        np.savez_compressed(
            file,
            sequences=np.array([r.sequence for r in results], dtype=str),
            frames=np.array([r.frame for r in results], dtype=np.int64),
            prediction_offsets=np.cumsum([0] + [len(p) for p in predictions]),
            predictions=np.concatenate(predictions + [np.zeros((0, 6))]),
            truth_offsets=np.cumsum([0] + [len(t) for t in truths]),
            ground_truth=np.concatenate(truths + [np.zeros((0, 5))]),
        )


def load_detections(path: Path) -> list[FrameDetections]:
    """npz written by save_detections -> one FrameDetections per frame. ValueError when it is not one."""
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {
                name: data[name]
                for name in (
                    "sequences",
                    "frames",
                    "prediction_offsets",
                    "predictions",
                    "truth_offsets",
                    "ground_truth",
                )
            }
    except (OSError, ValueError, KeyError) as error:
        raise ValueError(f"{path}: not a detections file written by rafd-eval --detections ({error})") from error
    p_off, t_off = arrays["prediction_offsets"], arrays["truth_offsets"]
    return [
        FrameDetections(
            str(name),
            int(frame),
            arrays["predictions"][p_off[i] : p_off[i + 1]],
            arrays["ground_truth"][t_off[i] : t_off[i + 1]],
        )
        for i, (name, frame) in enumerate(zip(arrays["sequences"], arrays["frames"]))
    ]


class _Scored:
    """One model's detections reduced to what the metrics need, so that any weighting of frames is cheap."""

    def __init__(self, frames: Sequence[FrameDetections]):
        predictions, truths = [f.predictions for f in frames], [f.ground_truth for f in frames]
        outcomes = ranked_outcomes(predictions, truths, IOU_THRESHOLDS)
        centres = match_centres(predictions, truths, CENTRE_DISTANCE_M)
        self.iou = [(outcomes.frames, outcomes.true_positive[float(t)]) for t in IOU_THRESHOLDS]
        assert centres.frames is not None  # match_centres fills it
        self.centre = (centres.frames, centres.true_positive)
        self.num_gt = outcomes.num_gt_per_frame.astype(np.float64)

    def metrics(self, frame_weights: np.ndarray) -> dict[str, float]:
        """Percent figures with every frame counted `frame_weights[f]` times."""
        num_gt = float(frame_weights @ self.num_gt)
        out = {}
        for name, (frames, tp) in zip(METRICS, self.iou):
            out[name] = 100.0 * ap_from_counts(*ranked_counts(tp, frame_weights[frames]), num_gt)
        frames, tp = self.centre
        tp_counts, fp_counts = ranked_counts(tp, frame_weights[frames])
        out["centre_AP"] = 100.0 * ap_from_counts(tp_counts, fp_counts, num_gt)
        last = last_within_fp_budget(fp_counts, float(frame_weights.sum()))  # 1 false positive per frame
        out["recall_at_1fp"] = 100.0 * float(tp_counts[last] / num_gt) if last is not None and num_gt > 0 else 0.0
        return out


def paired_bootstrap(
    baseline: Sequence[FrameDetections],
    candidate: Sequence[FrameDetections],
    resamples: int = 2000,
    seed: int = 0,
    confidence: float = 0.95,
) -> dict[str, dict[str, float]]:
    """Metric -> {baseline, candidate, difference (candidate - baseline), low, high (the central `confidence`
    interval of the difference over drive resamples), p_better (share of resamples where the candidate is ahead)}.
    Both must hold the same frames (sequence, frame) in any order."""
    if resamples < 1 or not 0 < confidence < 1:
        raise ValueError("resamples must be >= 1 and confidence in (0, 1)")
    keys = [(f.sequence, f.frame) for f in baseline]
    by_key = {(f.sequence, f.frame): f for f in candidate}
    if len(set(keys)) != len(keys) or set(keys) != set(by_key) or len(by_key) != len(candidate):
        missing = len(set(keys) ^ set(by_key))
        raise ValueError(
            f"the two detection sets do not cover the same frames ({missing} frames in only one; "
            "score both with the same rafd-eval data, split and --like-frames)"
        )
    if not keys:
        raise ValueError("no frames to compare")
    candidate = [by_key[k] for k in keys]  # frame f of both lists is the same frame
    drives = sorted({s for s, _ in keys})
    drive_of_frame = np.array([drives.index(s) for s, _ in keys])
    a, b = _Scored(baseline), _Scored(candidate)
    ones = np.ones(len(keys))
    observed_a, observed_b = a.metrics(ones), b.metrics(ones)
    rng = np.random.default_rng(seed)
    differences = {name: np.empty(resamples) for name in METRICS}
    for r in range(resamples):
        drawn = np.bincount(rng.integers(len(drives), size=len(drives)), minlength=len(drives)).astype(np.float64)
        weights = drawn[drive_of_frame]
        ma, mb = a.metrics(weights), b.metrics(weights)
        for name in METRICS:
            differences[name][r] = mb[name] - ma[name]
    tail = 100.0 * (1.0 - confidence) / 2.0
    return {
        name: {
            "baseline": observed_a[name],
            "candidate": observed_b[name],
            "difference": observed_b[name] - observed_a[name],
            "low": float(np.percentile(differences[name], tail)),
            "high": float(np.percentile(differences[name], 100.0 - tail)),
            "p_better": float(np.mean(differences[name] > 0)),
        }
        for name in METRICS
    }


def format_comparison(
    result: dict[str, dict[str, float]],
    baseline: str,
    candidate: str,
    drives: int,
    resamples: int,
    confidence: float = 0.95,
) -> str:
    """Markdown table of paired_bootstrap's result."""
    level = f"{100 * confidence:g}%"
    lines = [
        f"paired bootstrap over {drives} drives ({resamples} resamples): {candidate} - {baseline}",
        "",
        f"| metric | {baseline} | {candidate} | difference | {level} interval | share of resamples ahead |",
        "|---|---|---|---|---|---|",
    ]
    for name, row in result.items():
        lines.append(
            f"| {name} | {row['baseline']:.2f} | {row['candidate']:.2f} | {row['difference']:+.2f} | "
            f"[{row['low']:+.2f}, {row['high']:+.2f}] | {100 * row['p_better']:.0f}% |"
        )
    return "\n".join(lines)
