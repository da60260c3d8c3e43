"""Evaluation metrics: DOTA-style oriented-box mAP (one class) and flow end-point error (numpy + shapely).

Detection AP follows the DOTA devkit's `dota_evaluation_task1.voc_eval`:
- all detections of all frames are ranked by score, highest first (ties keep input order: frame,
  then index within the frame; the devkit's unstable argsort leaves ties arbitrary);
- a detection looks at the GT of its own frame with the highest polygon IoU (over ALL of that
  frame's GT, matched or not, first one on ties); it is a true positive when that IoU is strictly
  greater than the threshold and that GT is still unmatched; when that best GT is already matched
  the detection is a false positive (a duplicate), even if another GT also overlaps it enough;
- recall = TP / #GT, precision = TP / (TP + FP); AP is the VOC07 11-point interpolation by default,
  or the area under the monotone precision envelope (all-point) when `use_07_metric=False`.
Deviations, all at degenerate inputs where the devkit divides by zero: no GT at all gives AP 0.0
(no recall is achievable; the devkit yields nan), and no detections give AP 0.0.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import shapely

from rafd.geometry import box_corners
from rafd.protocol import IOU_THRESHOLDS


# ---------------------------------------------------------------- oriented-box IoU
def _as_boxes(boxes: np.ndarray, columns: int, name: str) -> np.ndarray:
    """Any array-like of boxes -> float64 [N, columns]; empty inputs become [0, columns]; NaN/negative sizes raise."""
    array = np.asarray(boxes, dtype=np.float64)
    if array.size == 0:
        return np.zeros((0, columns))
    if array.ndim == 1 and array.shape[0] == columns:
        array = array[None]
    if array.ndim != 2 or array.shape[1] != columns:
        raise ValueError(f"{name}: expected shape [N, {columns}], got {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{name}: contains NaN or infinite values")
    if np.any(array[:, 2:4] < 0):
        raise ValueError(f"{name}: negative width or length")
    return array


def _polygons(boxes: np.ndarray) -> np.ndarray:
    """[N, 5] boxes -> [N] shapely polygons of their corners."""
    return shapely.polygons(box_corners(boxes))  # corners [N, 4, 2]


def rotated_iou(boxes_a: np.ndarray, boxes_b: np.ndarray) -> np.ndarray:
    """Polygon IoU of oriented boxes: [N, 5] x [M, 5] -> [N, M] (0 where the union is empty).

    shapely, not opencv: opencv 5.0's rotatedRectangleIntersection and intersectConvexConvex both
    return wrong areas when edges are collinear and overlapping (a box shifted along its own
    length), which is exactly the near-threshold case of the benchmark.
    """
    boxes_a = _as_boxes(boxes_a, 5, "boxes_a")
    boxes_b = _as_boxes(boxes_b, 5, "boxes_b")
    ious = np.zeros((len(boxes_a), len(boxes_b)))
    if ious.size == 0:
        return ious
    # Bounding-circle prefilter: only pairs whose circumcircles overlap can intersect.
    radius_a = np.hypot(boxes_a[:, 2], boxes_a[:, 3]) / 2.0  # [N]
    radius_b = np.hypot(boxes_b[:, 2], boxes_b[:, 3]) / 2.0  # [M]
    distance = np.linalg.norm(boxes_a[:, None, :2] - boxes_b[None, :, :2], axis=-1)  # [N, M]
    area_a = boxes_a[:, 2] * boxes_a[:, 3]
    area_b = boxes_b[:, 2] * boxes_b[:, 3]
    candidates = (distance < radius_a[:, None] + radius_b[None, :]) & (area_a[:, None] > 0) & (area_b[None, :] > 0)
    if not candidates.any():
        return ious
    rows, cols = np.nonzero(candidates)
    # Relative to each pair's first centre: keeps float precision for boxes far from the origin.
    local_a = boxes_a[rows].copy()
    local_b = boxes_b[cols].copy()
    local_b[:, :2] -= local_a[:, :2]
    local_a[:, :2] = 0.0
    inter = shapely.area(shapely.intersection(_polygons(local_a), _polygons(local_b)))  # [P]
    union = area_a[rows] + area_b[cols] - inter
    ious[rows, cols] = np.where(union > 0, np.minimum(inter / np.where(union > 0, union, 1.0), 1.0), 0.0)
    return ious


# ---------------------------------------------------------------- average precision
def voc_ap(recall: np.ndarray, precision: np.ndarray, use_07_metric: bool = True) -> float:
    """AP from recall/precision in ranking order: VOC07 11-point, or all-point area under the envelope."""
    recall = np.asarray(recall, dtype=np.float64)
    precision = np.asarray(precision, dtype=np.float64)
    if recall.size == 0:
        return 0.0
    if use_07_metric:
        total = 0.0
        for t in np.arange(0.0, 1.1, 0.1):  # the devkit's exact thresholds (float steps included)
            reached = recall >= t
            total += float(np.max(precision[reached])) if reached.any() else 0.0
        # Divide once: eleven additions of p/11 give 1.0000000000000002 for a perfect ranking.
        return total / 11.0
    mrec = np.concatenate(([0.0], recall, [1.0]))
    mpre = np.concatenate(([0.0], precision, [0.0]))
    mpre = np.maximum.accumulate(mpre[::-1])[::-1]  # monotone envelope from the right
    steps = np.flatnonzero(mrec[1:] != mrec[:-1])
    return float(np.sum((mrec[steps + 1] - mrec[steps]) * mpre[steps + 1]))


def ranked_counts(true_positive: np.ndarray, weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Cumulative (true, false) positives down a ranking [D] bool; with `weights` [D] each detection counts that many
    times and those of weight 0 drop out (rafd.eval.compare's resampled frames)."""
    true_positive = np.asarray(true_positive, dtype=bool)
    if weights is None:
        return np.cumsum(true_positive, dtype=np.float64), np.cumsum(~true_positive, dtype=np.float64)
    keep = weights > 0
    return np.cumsum(weights[keep] * true_positive[keep]), np.cumsum(weights[keep] * ~true_positive[keep])


def ap_from_counts(tp: np.ndarray, fp: np.ndarray, num_gt: float, use_07_metric: bool = True) -> float:
    """AP from ranked_counts; 0 without ground truth or detections."""
    if num_gt <= 0 or not len(tp):
        return 0.0
    return voc_ap(tp / num_gt, tp / np.maximum(tp + fp, np.finfo(np.float64).eps), use_07_metric)


def last_within_fp_budget(fp: np.ndarray, max_false_positives: float) -> int | None:
    """Deepest rank whose cumulative false positives (ranked_counts) stay within the budget; None when none does."""
    allowed = np.flatnonzero(fp <= max_false_positives)
    return int(allowed[-1]) if len(allowed) else None


def _prepare(
    predictions: Sequence[np.ndarray], ground_truths: Sequence[np.ndarray]
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Validate per-frame lists -> ([N_f, 6], [M_f, 5]) float64 arrays, one pair per frame."""
    if len(predictions) != len(ground_truths):
        raise ValueError(f"{len(predictions)} prediction frames but {len(ground_truths)} ground-truth frames")
    preds = [_as_boxes(p, 6, f"predictions[{f}]") for f, p in enumerate(predictions)]
    gts = [_as_boxes(g, 5, f"ground_truths[{f}]") for f, g in enumerate(ground_truths)]
    return preds, gts


def _ranked_overlaps(preds: list[np.ndarray], gts: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rank detections over all frames -> (frame [D], best GT index [D] (-1: none), best IoU [D] (-inf: none))."""
    frames = np.concatenate([np.full(len(p), f) for f, p in enumerate(preds)] + [np.zeros(0, dtype=int)]).astype(int)
    scores = np.concatenate([p[:, 5] for p in preds] + [np.zeros(0)])
    best_gt = np.full(len(scores), -1)
    best_iou = np.full(len(scores), -np.inf)
    start = 0
    for pred, gt in zip(preds, gts):
        if len(pred) and len(gt):
            ious = rotated_iou(pred[:, :5], gt)  # [N_f, M_f]
            best_gt[start : start + len(pred)] = np.argmax(ious, 1)
            best_iou[start : start + len(pred)] = np.max(ious, 1)
        start += len(pred)
    order = np.argsort(-scores, kind="stable")
    return frames[order], best_gt[order], best_iou[order]


def _greedy_true_positives(
    frames: np.ndarray, best_gt: np.ndarray, best_iou: np.ndarray, num_gt_per_frame: list[int], iou_threshold: float
) -> np.ndarray:
    """Greedy matching in ranking order -> true positive [D] bool (a detection's fate depends on its own frame
    only: on the higher-ranked detections of that frame)."""
    if not 0.0 <= iou_threshold < 1.0:
        raise ValueError(f"IoU threshold must lie in [0, 1), got {iou_threshold}")
    matched = [np.zeros(n, dtype=bool) for n in num_gt_per_frame]
    true_positive = np.zeros(len(frames), dtype=bool)
    for d, (frame, gt, iou) in enumerate(zip(frames, best_gt, best_iou)):
        if iou > iou_threshold and not matched[frame][gt]:
            matched[frame][gt] = True
            true_positive[d] = True
    return true_positive


def _pr_from_overlaps(
    frames: np.ndarray, best_gt: np.ndarray, best_iou: np.ndarray, num_gt_per_frame: list[int], iou_threshold: float
) -> tuple[np.ndarray, np.ndarray]:
    """Greedy matching in ranking order -> (precision [D], recall [D])."""
    tp, fp = ranked_counts(_greedy_true_positives(frames, best_gt, best_iou, num_gt_per_frame, iou_threshold))
    num_gt = sum(num_gt_per_frame)
    recall = tp / num_gt if num_gt > 0 else np.zeros_like(tp)
    precision = tp / np.maximum(tp + fp, np.finfo(np.float64).eps)
    return precision, recall


def precision_recall(
    predictions: Sequence[np.ndarray],
    ground_truths: Sequence[np.ndarray],
    iou_threshold: float,
    use_07_metric: bool = True,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Per-frame predictions [N_f, 6] and GT [M_f, 5] -> (precision [D], recall [D], AP) in ranking order."""
    preds, gts = _prepare(predictions, ground_truths)
    frames, best_gt, best_iou = _ranked_overlaps(preds, gts)
    precision, recall = _pr_from_overlaps(frames, best_gt, best_iou, [len(g) for g in gts], iou_threshold)
    ap = voc_ap(recall, precision, use_07_metric) if sum(len(g) for g in gts) > 0 else 0.0
    return precision, recall, ap


def mean_average_precision(
    predictions: Sequence[np.ndarray],
    ground_truths: Sequence[np.ndarray],
    iou_thresholds: Sequence[float] = IOU_THRESHOLDS,
    use_07_metric: bool = True,
) -> dict[float, float]:
    """Per-frame predictions [N_f, 6] (x, y, w, l, yaw, score) and GT [M_f, 5] -> {IoU threshold: AP}.

    One class, so mAP at a threshold is that threshold's AP. IoUs are computed once and reused (ranked_outcomes).
    """
    outcomes = ranked_outcomes(predictions, ground_truths, iou_thresholds)
    num_gt = int(outcomes.num_gt_per_frame.sum())
    return {
        threshold: ap_from_counts(*ranked_counts(tp), num_gt, use_07_metric)
        for threshold, tp in outcomes.true_positive.items()
    }


@dataclass(frozen=True)
class RankedOutcomes:
    """Every detection of a set of frames in the metrics' ranking order with its fate at each IoU threshold:
    what a resampling of frames (rafd.eval.compare) needs to recompute AP without recomputing any overlap."""

    frames: np.ndarray  # [D] index of the detection's frame
    true_positive: dict[float, np.ndarray]  # IoU threshold -> [D] bool
    num_gt_per_frame: np.ndarray  # [F]


def ranked_outcomes(
    predictions: Sequence[np.ndarray],
    ground_truths: Sequence[np.ndarray],
    iou_thresholds: Sequence[float] = IOU_THRESHOLDS,
) -> RankedOutcomes:
    """Per-frame predictions [N_f, 6] and GT [M_f, 5] -> RankedOutcomes: the ranking and greedy matching that
    mean_average_precision scores (and rafd.eval.compare re-weights)."""
    preds, gts = _prepare(predictions, ground_truths)
    frames, best_gt, best_iou = _ranked_overlaps(preds, gts)
    num_gt_per_frame = [len(g) for g in gts]
    return RankedOutcomes(
        frames=frames,
        true_positive={
            float(t): _greedy_true_positives(frames, best_gt, best_iou, num_gt_per_frame, float(t))
            for t in iou_thresholds
        },
        num_gt_per_frame=np.asarray(num_gt_per_frame, dtype=np.int64),
    )


# ---------------------------------------------------------------- centre-distance matching
@dataclass(frozen=True)
class CentreMatches:
    """Every detection of a set of frames ranked by score, greedily matched to the nearest unmatched GT centre."""

    scores: np.ndarray  # [D] descending
    true_positive: np.ndarray  # [D] bool
    num_gt: int
    num_frames: int
    frames: np.ndarray | None = None  # [D] index of each detection's frame
    # ranges from the radar (the ego origin), for figures per range band
    detection_range: np.ndarray | None = None  # [D] of each detection's centre
    matched_range: np.ndarray | None = None  # [D] of the vehicle a true positive matched (nan: false positive)
    vehicle_range: np.ndarray | None = None  # [G] of every ground-truth vehicle

    def by_range(self, score_threshold: float, edges_m: Sequence[float]) -> list[dict[str, float]]:
        """Per range band [edges[i], edges[i+1]) m: vehicles in it, the recall among them and the false positives
        per frame lying in it, of the detections scoring >= the threshold. A radar engineer's first question:
        where does the detector lose vehicles and where does it invent them?"""
        if self.matched_range is None or self.detection_range is None or self.vehicle_range is None:
            raise ValueError("by_range needs the ranges of the detections and vehicles (match_centres fills them)")
        keep = self.scores >= score_threshold
        found, false = self.matched_range[keep & self.true_positive], self.detection_range[keep & ~self.true_positive]
        bands = []
        for low, high in zip(edges_m[:-1], edges_m[1:]):
            vehicles = int(((self.vehicle_range >= low) & (self.vehicle_range < high)).sum())
            hits = int(((found >= low) & (found < high)).sum())
            bands.append(
                {
                    "from_m": float(low),
                    "to_m": float(high),
                    "vehicles": vehicles,
                    "recall": 100.0 * hits / vehicles if vehicles else float("nan"),
                    "fp_per_frame": float(((false >= low) & (false < high)).sum() / max(self.num_frames, 1)),
                }
            )
        return bands

    def at_threshold(self, score_threshold: float) -> tuple[float, float]:
        """(recall, false positives per frame) of the detections scoring >= the threshold."""
        keep = self.scores >= score_threshold
        recall = float(self.true_positive[keep].sum() / self.num_gt) if self.num_gt else float("nan")
        return recall, float((~self.true_positive[keep]).sum() / max(self.num_frames, 1))

    def recall_at_fp_rate(self, fp_per_frame: float = 1.0) -> tuple[float, float]:
        """(highest recall reached with at most `fp_per_frame` false positives per frame, the score threshold that
        reaches it; inf when even the best detection is a false positive beyond the budget)."""
        tp, fp = ranked_counts(self.true_positive)
        last = last_within_fp_budget(fp, fp_per_frame * self.num_frames)
        if last is None or not self.num_gt:
            return 0.0, float("inf")
        return float(tp[last] / self.num_gt), float(self.scores[last])

    def average_precision(self, use_07_metric: bool = True) -> float:
        return ap_from_counts(*ranked_counts(self.true_positive), self.num_gt, use_07_metric)


def match_centres(
    predictions: Sequence[np.ndarray], ground_truths: Sequence[np.ndarray], max_distance: float = 2.0
) -> CentreMatches:
    """Per-frame predictions [N_f, 6] and GT [M_f, 5] -> CentreMatches: in descending score order, a detection is a
    true positive when the nearest GT centre of its frame that is still unmatched lies within max_distance metres."""
    preds, gts = _prepare(predictions, ground_truths)
    order_scores = [(p[:, 5], f) for f, p in enumerate(preds)]
    scores = np.concatenate([s for s, _ in order_scores] + [np.zeros(0)])
    frames = np.concatenate([np.full(len(s), f) for s, f in order_scores] + [np.zeros(0, int)]).astype(int)
    rows = np.concatenate([np.arange(len(p)) for p in preds] + [np.zeros(0, int)]).astype(int)
    order = np.argsort(-scores, kind="stable")
    matched = [np.zeros(len(g), bool) for g in gts]
    true_positive = np.zeros(len(order), bool)
    matched_range = np.full(len(order), np.nan)
    for rank, d in enumerate(order):
        gt = gts[frames[d]]
        if not len(gt):
            continue
        distance = np.hypot(*(gt[:, :2] - preds[frames[d]][rows[d], :2]).T)
        distance[matched[frames[d]]] = np.inf
        best = int(np.argmin(distance))
        if distance[best] <= max_distance:
            matched[frames[d]][best] = True
            true_positive[rank] = True
            matched_range[rank] = np.hypot(*gt[best, :2])
    centres = np.concatenate([p[:, :2] for p in preds] + [np.zeros((0, 2))])[order]
    vehicles = np.concatenate([g[:, :2] for g in gts] + [np.zeros((0, 2))])
    return CentreMatches(
        scores[order],
        true_positive,
        sum(len(g) for g in gts),
        len(gts),
        frames[order],
        detection_range=np.hypot(*centres.T),
        matched_range=matched_range,
        vehicle_range=np.hypot(*vehicles.T),
    )


# ---------------------------------------------------------------- flow
def end_point_error_terms(
    pred_flow: np.ndarray, gt_flow: np.ndarray, mask: np.ndarray | None = None
) -> tuple[float, int]:
    """[..., 2, H, W] flows (+ mask [..., 1, H, W]) -> (sum of per-cell L2 errors, number of cells counted).

    Use this to accumulate EPE over batches: total / count weights every cell equally.
    """
    pred = np.asarray(pred_flow, dtype=np.float64)
    gt = np.asarray(gt_flow, dtype=np.float64)
    if pred.shape != gt.shape:
        raise ValueError(f"pred_flow shape {pred.shape} differs from gt_flow shape {gt.shape}")
    if pred.ndim < 3 or pred.shape[-3] != 2:
        raise ValueError(f"flow must be [..., 2, H, W], got {pred.shape}")
    error = np.linalg.norm(pred - gt, axis=-3, keepdims=True)  # [..., 1, H, W]
    if mask is None:
        selected = np.ones(error.shape, dtype=bool)
    else:
        mask = np.asarray(mask)
        try:
            selected = np.broadcast_to(mask > 0, error.shape)
        except ValueError:
            raise ValueError(f"mask shape {mask.shape} does not broadcast to {error.shape}") from None
    chosen = error[selected]
    if not np.all(np.isfinite(chosen)):
        raise ValueError("pred_flow or gt_flow holds NaN/inf inside the evaluated region")
    return float(chosen.sum()), int(chosen.size)


def end_point_error(pred_flow: np.ndarray, gt_flow: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean L2 norm of pred - gt over axis -3 ([..., 2, H, W]) where mask > 0; nan when no cell is selected.

    An empty selection returns nan rather than 0: no cells means no evidence, and 0 would read as a
    perfect flow. Non-finite values inside the selection raise; values outside the mask are ignored.
    """
    total, count = end_point_error_terms(pred_flow, gt_flow, mask)
    return total / count if count else float("nan")
