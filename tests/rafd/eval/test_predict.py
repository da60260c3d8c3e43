"""Summaries of per-frame results: mAP in percent, EPE pooled over cells, per-sequence split."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rafd.eval.predict import FrameResult, summarise, summarise_by_condition, summarise_by_sequence


def _result(sequence: str, gt: np.ndarray, pred: np.ndarray, epe: float, cells: int) -> FrameResult:
    return FrameResult(
        sequence=sequence,
        frame=1,
        predictions=pred,
        ground_truth=gt,
        epe_all=epe,
        epe_foreground=math.nan,
        cells_all=cells,
        cells_foreground=0,
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


def test_conditions_pool_their_sequences_and_unnamed_ones_are_unknown() -> None:
    gt = np.array([[2.0, 5.0, 1.8, 4.5, 0.3]])
    hit, miss = np.concatenate([gt, [[0.9]]], 1), np.array([[12.0, -5.0, 1.8, 4.5, 0.3, 0.9]])
    results = [
        _result("fog_a", gt, hit, 0.5, 4),
        _result("fog_b", gt, miss, 0.5, 4),
        _result("clear_a", gt, hit, 0.5, 4),
        _result("other", gt, miss, 0.5, 4),
    ]
    per_condition = summarise_by_condition(results, {"fog_a": "fog", "fog_b": "fog", "clear_a": "clear"}, 0.5)
    assert list(per_condition) == ["clear", "fog", "unknown"]
    assert per_condition["fog"]["frames"] == 2 and per_condition["fog"]["recall_at_threshold"] == pytest.approx(50.0)
    assert per_condition["clear"]["recall_at_threshold"] == pytest.approx(100.0)
    assert per_condition["unknown"]["fp_per_frame_at_threshold"] == pytest.approx(1.0)
    assert summarise_by_condition(results, {"fog_a": None}) == {}  # no sequence names a condition: no table


def test_past_as_newest_feeds_the_newest_frame_and_pose_in_every_slot(tiny_root, tiny_cfg) -> None:
    """The temporal ablation: the model sees T copies of the newest frame at the newest pose, and nothing else."""
    import torch
    from torch import nn

    from rafd.data.windows import open_windows
    from rafd.eval.predict import predict
    from rafd.model.build import build_model

    model = build_model(tiny_cfg).eval()
    seen = []

    class Recorder(nn.Module):
        def forward(self, frames, poses):
            seen.append((frames.clone(), poses.clone()))
            return model(frames, poses)

    dataset = open_windows(tiny_root, "train", tiny_cfg, None, augment=False)
    true = predict(Recorder(), dataset, tiny_cfg, batch_size=4, progress=False)
    true_frames, true_poses = seen.pop(0)
    seen.clear()
    ablated = predict(Recorder(), dataset, tiny_cfg, batch_size=4, progress=False, past_as_newest=True)
    frames, poses = seen[0]
    assert not torch.equal(true_frames[:, 0], true_frames[:, -1])  # the real windows do hold other frames
    for t in range(frames.shape[1]):
        assert torch.equal(frames[:, t], true_frames[:, -1]) and torch.equal(poses[:, t], true_poses[:, -1])
    assert len(ablated) == len(true) and [r.frame for r in ablated] == [r.frame for r in true]
    # the same ablation by hand gives the same detections
    steps = frames.shape[1]
    with torch.no_grad():
        by_hand = model(true_frames[:, -1:].repeat(1, steps, 1, 1, 1), true_poses[:, -1:].repeat(1, steps, 1))
    np.testing.assert_allclose(
        ablated[0].predictions[:, 5], np.sort(by_hand["scores"][0].numpy())[::-1], rtol=1e-5, atol=1e-6
    )
