"""Run a model over a window dataset -> per-frame detections, GT boxes and flow EPE; summaries."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.utils.data import DataLoader, Dataset

from rafd.config import RaFDConfig
from rafd.data.collate import Collator
from rafd.detections import answered, decode_detections
from rafd.eval.flow_split import FlowTally, tally_pair
from rafd.eval.metrics import end_point_error, match_centres, mean_average_precision
from rafd.flow_validity import config_validity
from rafd.geometry import points_in_boxes, relative_pose
from rafd.progress import bar
from rafd.protocol import CENTRE_DISTANCE_M, IOU_THRESHOLDS, OperatingThreshold, as_operating_threshold


@dataclass
class FrameResult:
    sequence: str
    frame: int  # newest frame's RADIATE number
    predictions: np.ndarray  # [N, 6] (x, y, width, length, yaw, score), metres, best first
    ground_truth: np.ndarray  # [M, 5] every GT box of the newest frame (not truncated to K)
    # EPE of the newest pair (t-1, t): each consecutive pair of a sequence is counted once.
    epe_all: float  # mean L2 over cells with a defined target (flow_valid); nan without flow
    epe_foreground: float  # mean L2 over matched object regions (flow_foreground); nan when none
    cells_all: int  # number of cells behind epe_all (for pooled averages)
    cells_foreground: int
    flow: np.ndarray | None = None  # [2, Hf, Wf] predicted newest-pair flow (kept on request)
    gt_flow: np.ndarray | None = None  # [2, Hf, Wf]
    # the newest pair's flow by ring from the crop's edge, vehicles / background / label-free (rafd.eval.flow_split)
    flow_tally: FlowTally | None = None
    # full scans with keep_flow: the newest real pair's flow over the whole scan, one rafd.tracking.FlowField per
    # tile (a mosaic; None without a real pair), for the tracking evaluation (rafd.eval.tracking)
    flow_fields: tuple | None = None


def outside_ignored(predictions: np.ndarray, ignore: np.ndarray) -> np.ndarray:
    """[N, 6] predictions without those whose centre lies in a region the labeller left undecided ([K, 5] ignore
    boxes, rafd.data.labels.IGNORE_CLASS): such a detection is neither a true nor a false positive."""
    ignore = np.asarray(ignore, dtype=np.float64).reshape(-1, 5)
    if len(ignore) == 0 or len(predictions) == 0:
        return predictions
    return predictions[~points_in_boxes(predictions[:, :2], ignore).any(axis=1)]


def _epe(pred: np.ndarray, gt: np.ndarray, mask: np.ndarray) -> tuple[float, int]:
    """Mean EPE under a mask via rafd.eval.metrics and the number of cells it covers."""
    cells = int(mask.sum())
    if cells == 0:
        return math.nan, 0
    return float(end_point_error(pred, gt, mask.astype(bool))), cells


@torch.no_grad()
def predict(
    model: nn.Module,
    dataset: Dataset,
    cfg: RaFDConfig,
    device: torch.device | str = "cpu",
    batch_size: int = 8,
    score_threshold: float = 0.0,
    keep_flow: bool = False,
    progress: bool = True,
    num_workers: int = 0,
    precision: str = "fp32",
    past_as_newest: bool = False,
) -> list[FrameResult]:
    """Every window of `dataset` -> one FrameResult; all K queries kept by default (AP wants the tail).
    `precision` fp32 | bf16 | fp16 runs the forward under that autocast (rafd.model.precision).
    `past_as_newest` is the temporal ablation: every past frame of a window is replaced by the newest one, at the
    newest pose (a still world with nothing more to see), so a multi-frame model sees exactly what a single-frame
    model sees; its score against the true windows is what the past frames add."""
    from rafd.model.precision import autocast, check_precision

    device = torch.device(device)
    check_precision(precision, device)
    was_training = model.training
    model.eval()
    loader = DataLoader(
        dataset, batch_size=batch_size, shuffle=False, num_workers=num_workers, collate_fn=Collator(cfg)
    )
    results: list[FrameResult] = []
    try:
        for batch in bar(loader, desc="predict windows", unit="batch", enabled=progress):
            batch = batch.to(device)
            frames, poses = batch.frames, batch.poses  # [B, T, 1, S, S], [B, T, 3]
            if past_as_newest:
                frames, poses = frames[:, -1:].expand_as(frames), poses[:, -1:].expand_as(poses)
            with autocast(device, precision):
                outputs = model(frames, poses)
            boxes = outputs["boxes"].float().cpu().numpy()  # [B, K, 5]
            scores = outputs["scores"].float().cpu().numpy()  # [B, K]
            flow = outputs.get("flow")
            flow_np = (
                flow.float().cpu().numpy() if flow is not None and flow.shape[1] > 0 else None
            )  # [B, P, 2, Hf, Wf]
            gt_flow = batch.targets["flow"].cpu().numpy()
            valid = batch.targets["flow_valid"].cpu().numpy()
            foreground = batch.targets["flow_foreground"].cpu().numpy()
            relative = repeated = None
            if flow_np is not None:
                # the newest pair's ego motion and whether it pairs a frame with itself, as the model got them
                pose_pair = poses[:, -2:].double().cpu().numpy()  # [B, 2, 3]
                relative = relative_pose(pose_pair[:, 0], pose_pair[:, 1])  # [B, 3]
                repeated = [
                    bool(torch.equal(frames[b, -1], frames[b, -2]) and torch.equal(poses[b, -1], poses[b, -2]))
                    for b in range(len(batch))
                ]
            for b in range(len(batch)):
                detections = decode_detections(boxes[b], scores[b], score_threshold)
                epe_all = epe_fg = math.nan
                cells_all = cells_fg = 0
                pred_pair = gt_pair = tally = None
                if flow_np is not None and relative is not None and repeated is not None:
                    pred_pair, gt_pair = flow_np[b, -1], gt_flow[b, -1]  # [2, Hf, Wf]
                    epe_all, cells_all = _epe(pred_pair, gt_pair, valid[b, -1, 0] > 0)
                    epe_fg, cells_fg = _epe(pred_pair, gt_pair, (foreground[b, -1, 0] > 0) & (valid[b, -1, 0] > 0))
                    tally = tally_pair(
                        pred_pair,
                        config_validity(cfg, relative[b]),
                        gt_pair,
                        valid[b, -1, 0],
                        foreground[b, -1, 0],
                        repeated=repeated[b],
                    )
                results.append(
                    FrameResult(
                        sequence=batch.sequences[b],
                        frame=batch.frame_numbers[b],
                        predictions=outside_ignored(detections.as_array(), batch.ignore[b]),
                        ground_truth=batch.boxes[b],
                        epe_all=epe_all,
                        epe_foreground=epe_fg,
                        cells_all=cells_all,
                        cells_foreground=cells_fg,
                        flow=pred_pair if keep_flow else None,
                        gt_flow=gt_pair if keep_flow else None,
                        flow_tally=tally,
                    )
                )
    finally:
        model.train(was_training)
    return results


def _pooled(values: Sequence[float], weights: Sequence[int]) -> float:
    """Cell-weighted mean of per-frame means = the mean over all pooled cells."""
    total = sum(w for w in weights)
    if total == 0:
        return math.nan
    return float(sum(v * w for v, w in zip(values, weights) if w > 0) / total)


RANGE_BANDS_M = (0.0, 25.0, 50.0, 75.0, 100.0, float("inf"))  # the Navtech reaches 100 m; full-scan corners 141 m


def summarise(
    results: Sequence[FrameResult],
    iou_thresholds: Sequence[float] = IOU_THRESHOLDS,
    score_threshold: OperatingThreshold | float | None = None,
) -> dict[str, Any]:
    """mAP@IoU (in percent, like the paper's tables), centre-distance detection figures and pooled EPE:
    centre_AP (VOC AP with centre within CENTRE_DISTANCE_M as the match), recall_at_1fp (recall with at most one
    false positive per frame, and the score threshold that gives it), and with a score_threshold its recall and
    false positives per frame, overall and by range: of the detections it answers (rafd.detections.answered, the
    service's rule), matched among themselves."""
    summary: dict[str, Any] = {"frames": len(results)}
    if not results:
        return summary
    predictions, ground_truths = [r.predictions for r in results], [r.ground_truth for r in results]
    aps = mean_average_precision(predictions, ground_truths, iou_thresholds=tuple(iou_thresholds))
    for threshold in iou_thresholds:
        summary[f"mAP@{threshold:g}"] = 100.0 * float(aps[threshold])
    centres = match_centres(predictions, ground_truths, CENTRE_DISTANCE_M)
    summary["centre_AP"] = 100.0 * centres.average_precision()
    recall, threshold_at = centres.recall_at_fp_rate(1.0)
    summary["recall_at_1fp"] = 100.0 * recall
    summary["threshold_at_1fp"] = threshold_at
    if score_threshold is not None:
        answering = as_operating_threshold(score_threshold)
        kept = match_centres([answered(p, answering) for p in predictions], ground_truths, CENTRE_DISTANCE_M)
        recall, fp_per_frame = kept.at_threshold(0.0)
        summary["score_threshold"] = answering.near
        summary["far_score_threshold"] = answering.far_json()
        summary["recall_at_threshold"] = 100.0 * recall
        summary["fp_per_frame_at_threshold"] = fp_per_frame
        summary["by_range_at_threshold"] = kept.by_range(0.0, RANGE_BANDS_M)
    summary["epe_all"] = _pooled([r.epe_all for r in results], [r.cells_all for r in results])
    summary["epe_foreground"] = _pooled([r.epe_foreground for r in results], [r.cells_foreground for r in results])
    summary["objects"] = int(sum(len(r.ground_truth) for r in results))
    return summary


def _summarise_groups(
    results: Sequence[FrameResult], group_of: Mapping[str, str], score_threshold: OperatingThreshold | float | None
) -> dict[str, dict[str, Any]]:
    """Summaries pooled over the frames of each group ({sequence name: group}), keyed by group (sorted)."""
    return {
        group: summarise([r for r in results if group_of[r.sequence] == group], score_threshold=score_threshold)
        for group in sorted(set(group_of.values()))
    }


def summarise_by_condition(
    results: Sequence[FrameResult],
    conditions: Mapping[str, str | None],
    score_threshold: OperatingThreshold | float | None = None,
) -> dict[str, dict[str, Any]]:
    """Summaries pooled over the sequences of each recording condition ({sequence name: condition}: the
    simulator's weather, RADIATE's type such as fog), keyed by condition (sorted); sequences without one are
    pooled as "unknown". {} when no sequence names a condition."""
    if not any(conditions.get(r.sequence) for r in results):
        return {}
    return _summarise_groups(
        results, {r.sequence: conditions.get(r.sequence) or "unknown" for r in results}, score_threshold
    )


def summarise_by_sequence(
    results: Sequence[FrameResult], score_threshold: OperatingThreshold | float | None = None
) -> dict[str, dict[str, Any]]:
    """Per-sequence summaries, keyed by sequence name (sorted)."""
    return _summarise_groups(results, {r.sequence: r.sequence for r in results}, score_threshold)
