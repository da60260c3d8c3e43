"""rafd.eval.far_threshold: the far threshold is the lowest on its grid whose false positives per frame have a 95%
upper bound (bootstrap over sequences) within the budget; the near detections are never touched."""

from __future__ import annotations

import numpy as np

from rafd.eval.far_threshold import STEP, calibrate_far, false_positives_per_frame, upper_bound
from rafd.protocol import OperatingThreshold


def scans(sequences: int = 6, frames: int = 10, seed: int = 0):
    """Each scan: one vehicle at 20 m found at 0.9, one at 70 m found at a random score, and far false positives
    at random scores (more in some sequences than others)."""
    rng = np.random.default_rng(seed)
    predictions, truths, names = [], [], []
    for s in range(sequences):
        for _ in range(frames):
            truth = np.array([[0.0, 20.0, 2, 4, 0], [0.0, 70.0, 2, 4, 0]])
            rows = [[0.0, 20.0, 2, 4, 0, 0.9], [0.0, 70.3, 2, 4, 0, rng.uniform(0.3, 0.9)]]
            rows += [[rng.uniform(-80, 80), -70.0, 2, 4, 0, rng.uniform(0.3, 0.7)] for _ in range(1 + s % 3)]
            rows += [[10.0, -10.0, 2, 4, 0, 0.36]]  # a near false positive above the near threshold: always kept
            predictions.append(np.array(rows))
            truths.append(truth)
            names.append(f"drive_{s}")
    return predictions, truths, names


def test_the_chosen_threshold_is_the_lowest_on_the_grid_within_the_budget():
    predictions, truths, names = scans()
    index = np.array([sorted(set(names)).index(n) for n in names])
    found = calibrate_far(predictions, truths, names, near=0.35, from_m=50.0, budget=2.0)
    assert np.isfinite(found.threshold) and found.fp_per_frame_bound <= 2.0
    below = OperatingThreshold(0.35, far=round(found.threshold - STEP, 6), far_from_m=50.0)
    counts, _ = false_positives_per_frame(predictions, truths, below)
    assert upper_bound(counts, index) > 2.0  # one step lower would break the budget
    assert found.fp_per_frame >= 1.0  # the near false positive stays in every scan
    assert 0.0 < found.recall_beyond < 1.0 and (found.frames, found.sequences) == (60, 6)


def test_no_threshold_when_the_near_detections_alone_break_the_budget():
    predictions, truths, names = scans()
    found = calibrate_far(predictions, truths, names, near=0.35, from_m=50.0, budget=0.5)
    assert found.threshold == float("inf")


def test_the_bound_lies_above_the_mean_when_sequences_differ():
    counts = np.array([0.0] * 10 + [4.0] * 10)
    bound = upper_bound(counts, np.repeat([0, 1], 10))
    assert counts.mean() < bound <= 4.0
    assert upper_bound(np.full(20, 1.0), np.repeat([0, 1], 10)) == 1.0
