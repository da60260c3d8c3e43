"""Summaries of per-frame results: mAP in percent, EPE pooled over cells, per-sequence split."""
from __future__ import annotations

import math

import numpy as np
import pytest

from rafd.train.predict import FrameResult, summarise, summarise_by_sequence


def _result(sequence: str, gt: np.ndarray, pred: np.ndarray, epe: float, cells: int) -> FrameResult:
    return FrameResult(
        sequence=sequence, frame=1, predictions=pred, ground_truth=gt,
        epe_all=epe, epe_foreground=math.nan, cells_all=cells, cells_foreground=0,
    )


def test_perfect_predictions_give_full_map_and_pooled_epe() -> None:
    gt = np.array([[2.0, 5.0, 1.8, 4.5, 0.3], [-6.0, -3.0, 2.0, 5.0, -1.0]])
    pred = np.concatenate([gt, np.array([[0.9], [0.8]])], 1)
    results = [_result("a", gt, pred, epe=1.0, cells=10), _result("b", gt[:1], pred[:1], epe=4.0, cells=30)]
    summary = summarise(results)
    for threshold in ("0.3", "0.5", "0.7"):
        assert summary[f"mAP@{threshold}"] == pytest.approx(100.0)
    assert summary["epe_all"] == pytest.approx((1.0 * 10 + 4.0 * 30) / 40)  # pooled, not mean of means
    assert math.isnan(summary["epe_foreground"])
    assert summary["objects"] == 3 and summary["frames"] == 2


def test_missed_and_wrong_boxes_lower_map_and_sequences_are_split() -> None:
    gt = np.array([[2.0, 5.0, 1.8, 4.5, 0.3]])
    wrong = np.array([[12.0, -5.0, 1.8, 4.5, 0.3, 0.9]])
    results = [_result("good", gt, np.concatenate([gt, [[0.9]]], 1), 0.5, 4), _result("bad", gt, wrong, 0.5, 4)]
    per_sequence = summarise_by_sequence(results)
    assert list(per_sequence) == ["bad", "good"]
    assert per_sequence["good"]["mAP@0.5"] == pytest.approx(100.0)
    assert per_sequence["bad"]["mAP@0.5"] == pytest.approx(0.0)
    assert 0.0 < summarise(results)["mAP@0.5"] < 100.0
