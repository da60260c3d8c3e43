"""tools.real_cv: the fold plan holds every group out once, per-scan counts at a fold's threshold follow centre
matching, and the pooled recall and its bootstrap interval come from the scans' counts."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from rafd.eval.compare import save_detections
from tools.real_cv import ScanCounts, folds, pooled, scan_counts


def test_every_group_is_held_out_once_and_never_trained_on_in_its_fold() -> None:
    plan = folds(["a", "b", "c"])
    assert [held for held, _ in plan] == ["a", "b", "c"]
    assert all(held not in training and len(training) == 2 for held, training in plan)
    with pytest.raises(ValueError):
        folds(["a"])
    with pytest.raises(ValueError):
        folds(["a", "a"])


def test_scan_counts_keep_the_detections_at_or_above_the_threshold(tmp_path: Path) -> None:
    truth = np.array([[0.0, 10.0, 2.0, 4.5, 0.0], [5.0, -8.0, 2.0, 4.5, 0.0]])
    predictions = np.array(
        [
            [0.5, 10.5, 2.0, 4.5, 0.0, 0.9],  # finds the first vehicle
            [20.0, 20.0, 2.0, 4.5, 0.0, 0.6],  # a false positive
            [5.0, -8.0, 2.0, 4.5, 0.0, 0.2],  # would find the second one, but is under the threshold
        ]
    )
    frame = SimpleNamespace(sequence="s", frame=3, predictions=predictions, ground_truth=truth)
    save_detections(tmp_path / "d.npz", [frame])
    (counts,) = scan_counts("g", tmp_path / "d.npz", threshold=0.5)
    assert (counts.vehicles, counts.found, counts.false_positives) == (2, 1, 1)
    (lower,) = scan_counts("g", tmp_path / "d.npz", threshold=0.1)
    assert (lower.found, lower.false_positives) == (2, 1)


def test_pooled_recall_is_found_over_vehicles_with_an_interval_around_it() -> None:
    scans = [ScanCounts("a", "s", i, 2, found, fp) for i, (found, fp) in enumerate([(2, 0), (1, 1), (0, 2), (1, 1)])]
    result = pooled(scans, resamples=500)
    assert result["vehicles"] == 8 and result["found"] == 4
    assert result["recall"] == pytest.approx(50.0)
    assert result["fp_per_scan"] == pytest.approx(1.0)
    assert 0.0 <= result["recall_low"] < 50.0 < result["recall_high"] <= 100.0
    with pytest.raises(ValueError):
        pooled([ScanCounts("a", "s", 1, 0, 0, 1)])
