"""Calibration of the far operating threshold (`rafd eval --calibrate-far FROM_M:FP`).

A whole scan's false positives grow with range (fewer returns per vehicle, more clutter per cell), while real labels
rarely reach beyond a few tens of metres: the near threshold is calibrated on real scans, and the far one, for the
detections `from_m` or more from the radar, on whole scans of validation data. It is the lowest threshold at which
the whole scan's false positives per scan stay within the budget with 95% confidence over sequences: the 97.5th
percentile of a bootstrap over the sequences (drives differ more than scans of one drive) is at most the budget. A
point estimate within the budget on validation drives lands above it on other drives about half the time.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from rafd.detections import answered
from rafd.eval.metrics import match_centres
from rafd.protocol import CENTRE_DISTANCE_M, OperatingThreshold

RESAMPLES = 2000
STEP = 0.001  # thresholds are searched on this grid


@dataclass(frozen=True)
class FarCalibration:
    threshold: float  # the far threshold chosen (inf: none within the budget)
    fp_per_frame: float  # whole-scan false positives per frame at it
    fp_per_frame_bound: float  # their 95% upper bound (bootstrap over sequences)
    recall_beyond: float  # recall (0-1) of the vehicles from_m or more from the radar at it
    frames: int
    sequences: int


def false_positives_per_frame(
    predictions: Sequence[np.ndarray], ground_truths: Sequence[np.ndarray], threshold: OperatingThreshold
) -> tuple[np.ndarray, float]:
    """[N, 6] predictions and [G, 5] ground truths per frame -> ([F] false positives answered in each frame, recall
    of the vehicles beyond the far range), matching the detections answered among themselves (as the service
    answers them)."""
    kept = match_centres([answered(p, threshold) for p in predictions], ground_truths, CENTRE_DISTANCE_M)
    frames = np.asarray(kept.frames if kept.frames is not None else np.zeros(0), np.intp)
    counts = np.bincount(frames[~kept.true_positive], minlength=len(predictions)).astype(np.float64)  # [F]
    far = threshold.far_from_m if threshold.far_from_m is not None else np.inf
    assert kept.vehicle_range is not None and kept.matched_range is not None
    vehicles = int((kept.vehicle_range >= far).sum())
    found = int((kept.true_positive & (kept.matched_range >= far)).sum())
    return counts, found / vehicles if vehicles else float("nan")


def upper_bound(counts: np.ndarray, sequence_of_frame: np.ndarray, resamples: int = RESAMPLES, seed: int = 0) -> float:
    """[F] per-frame counts, [F] sequence index of each frame -> the 97.5th percentile of the mean count per frame
    over bootstrap resamples of the sequences."""
    sequences = int(sequence_of_frame.max()) + 1
    rng = np.random.default_rng(seed)
    drawn = rng.multinomial(sequences, np.full(sequences, 1.0 / sequences), size=resamples)  # [R, S] draws per seq
    weights = drawn[:, sequence_of_frame].astype(np.float64)  # [R, F]
    means = (weights * counts).sum(1) / np.maximum(weights.sum(1), 1.0)  # [R]
    return float(np.percentile(means, 97.5))


def calibrate_far(
    predictions: Sequence[np.ndarray],
    ground_truths: Sequence[np.ndarray],
    sequences: Sequence[str],
    near: float,
    from_m: float,
    budget: float,
) -> FarCalibration:
    """The lowest far threshold (>= near, on a STEP grid) whose whole-scan false positives per frame have a 95% upper
    bound within `budget`. The bound only falls as the far threshold rises (dropping a detection never adds a false
    positive), so the grid is bisected."""
    names = sorted(set(sequences))
    sequence_of_frame = np.array([names.index(s) for s in sequences], np.intp)  # [F]

    def measured(far: float) -> tuple[np.ndarray, float, float]:
        counts, recall = false_positives_per_frame(
            predictions, ground_truths, OperatingThreshold(near, far=far, far_from_m=from_m)
        )
        return counts, upper_bound(counts, sequence_of_frame), recall

    grid = np.round(np.arange(np.ceil(near / STEP) * STEP, 1.0 + STEP / 2, STEP), 6)  # [K] candidates, ascending
    low, high = 0, len(grid)  # the answer lies in grid[low:high], or none does (high == len(grid))
    while low < high:
        middle = (low + high) // 2
        if measured(float(grid[middle]))[1] <= budget:
            high = middle
        else:
            low = middle + 1
    if low == len(grid):
        return FarCalibration(float("inf"), float("nan"), float("nan"), float("nan"), len(predictions), len(names))
    counts, bound, recall = measured(float(grid[low]))
    return FarCalibration(float(grid[low]), float(counts.mean()), bound, recall, len(predictions), len(names))
