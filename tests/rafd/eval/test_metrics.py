"""DOTA-style oriented mAP and flow EPE on hand-made cases whose answers are worked out by hand."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from rafd.eval.metrics import (
    end_point_error,
    end_point_error_terms,
    mean_average_precision,
    precision_recall,
    rotated_iou,
    voc_ap,
)
from rafd.geometry import box_corners

YAWS = (0.0, 0.4, np.pi / 2, 2.5, -1.0)


def shifted_along_length(box: np.ndarray, distance: float) -> np.ndarray:
    """The same box moved `distance` metres along its own length axis, R(yaw) @ (0, 1)."""
    yaw = box[4]
    return box + np.array([-np.sin(yaw) * distance, np.cos(yaw) * distance, 0.0, 0.0, 0.0])


def shift_for_iou(length: float, iou: float) -> float:
    """Equal boxes shifted by d along their length have IoU (L - d) / (L + d); solve for d."""
    return length * (1.0 - iou) / (1.0 + iou)


def det(box, score) -> np.ndarray:
    return np.append(np.asarray(box, dtype=float), score)


# ---------------------------------------------------------------- rotated_iou
@pytest.mark.parametrize("yaw", YAWS)
def test_rotated_iou_of_a_box_with_itself_is_one(yaw):
    box = np.array([[3.0, -7.0, 1.8, 4.5, yaw]])
    assert rotated_iou(box, box)[0, 0] == pytest.approx(1.0, abs=1e-6)


def test_square_rotated_by_90_degrees_equals_itself():
    square = np.array([[10.0, 12.0, 2.0, 2.0, 0.3]])
    turned = square + np.array([[0, 0, 0, 0, np.pi / 2]])
    assert rotated_iou(square, turned)[0, 0] == pytest.approx(1.0, abs=1e-6)
    # width/length swapped with a 90-degree turn is the same rectangle too
    swapped = np.array([[10.0, 12.0, 4.0, 2.0, 0.3 + np.pi / 2]])
    assert rotated_iou(np.array([[10.0, 12.0, 2.0, 4.0, 0.3]]), swapped)[0, 0] == pytest.approx(1.0, abs=1e-6)


@pytest.mark.parametrize("yaw", YAWS)
@pytest.mark.parametrize("iou", (0.29, 0.31, 0.49, 0.51, 0.69, 0.71, 0.9))
def test_rotated_iou_matches_closed_form_for_shift_along_length(yaw, iou):
    box = np.array([20.0, -15.0, 1.9, 4.7, yaw])
    other = shifted_along_length(box, shift_for_iou(box[3], iou))
    assert rotated_iou(box[None], other[None])[0, 0] == pytest.approx(iou, abs=1e-6)


def test_rotated_iou_against_rasterised_areas_on_random_pairs():
    rng = np.random.default_rng(0)
    boxes_a = np.column_stack(
        [rng.uniform(-3, 3, (30, 2)), rng.uniform(0.5, 5, (30, 2)), rng.uniform(-np.pi, np.pi, 30)]
    )
    boxes_b = np.column_stack(
        [rng.uniform(-3, 3, (30, 2)), rng.uniform(0.5, 5, (30, 2)), rng.uniform(-np.pi, np.pi, 30)]
    )
    ious = rotated_iou(boxes_a, boxes_b)
    assert ious.shape == (30, 30)
    scale, size = 100.0, 1200  # 1 cm rasters of a 12 m square
    for i, j in [(k, k) for k in range(30)]:
        masks = []
        for box in (boxes_a[i], boxes_b[j]):
            mask = np.zeros((size, size), np.uint8)
            cv2.fillPoly(mask, [np.round((box_corners(box)[0] + 6.0) * scale).astype(np.int32)], 1)
            masks.append(mask.astype(bool))
        union = (masks[0] | masks[1]).sum()
        assert ious[i, j] == pytest.approx((masks[0] & masks[1]).sum() / union, abs=0.01)
    assert np.any(ious > 0.05) and np.any(ious == 0.0)  # the sample exercises both paths
    np.testing.assert_allclose(rotated_iou(boxes_b, boxes_a), ious.T, atol=1e-6)


def test_rotated_iou_degenerate_and_invalid_boxes():
    box = np.array([[0.0, 0.0, 2.0, 4.0, 0.2]])
    flat = np.array([[0.0, 0.0, 0.0, 4.0, 0.2]])
    assert rotated_iou(box, flat)[0, 0] == 0.0
    assert rotated_iou(flat, flat)[0, 0] == 0.0
    assert rotated_iou(np.zeros((0, 5)), box).shape == (0, 1)
    far = np.array([[100.0, 0.0, 2.0, 4.0, 0.2]])
    assert rotated_iou(box, far)[0, 0] == 0.0
    with pytest.raises(ValueError, match="NaN"):
        rotated_iou(np.array([[0.0, np.nan, 2.0, 4.0, 0.0]]), box)
    with pytest.raises(ValueError, match="negative"):
        rotated_iou(np.array([[0.0, 0.0, -2.0, 4.0, 0.0]]), box)
    with pytest.raises(ValueError, match=r"\[N, 5\]"):
        rotated_iou(np.zeros((2, 4)), box)


# ---------------------------------------------------------------- average precision
GT1 = np.array([0.0, 10.0, 2.0, 4.5, 0.3])
GT2 = np.array([8.0, -5.0, 1.8, 4.0, -1.2])


def test_perfect_detections_give_one():
    gts = [np.stack([GT1, GT2]), GT2[None]]
    preds = [np.stack([det(GT1, 0.9), det(GT2, 0.8)]), det(GT2, 0.7)[None]]
    for use_07 in (True, False):
        result = mean_average_precision(preds, gts, use_07_metric=use_07)
        assert set(result) == {0.3, 0.5, 0.7}
        assert all(ap == pytest.approx(1.0) for ap in result.values())


def test_one_of_two_gts_missed():
    gts = [np.stack([GT1, GT2])]
    preds = [det(GT1, 0.9)[None]]
    assert mean_average_precision(preds, gts)[0.5] == pytest.approx(6.0 / 11.0, abs=1e-12)
    assert mean_average_precision(preds, gts, use_07_metric=False)[0.5] == pytest.approx(0.5, abs=1e-12)


def test_duplicates_are_false_positives():
    # ranking TP (GT1), FP (second hit on GT1), TP (GT2): recall .5 .5 1, precision 1 .5 2/3
    gts = [np.stack([GT1, GT2])]
    near_gt1 = shifted_along_length(GT1, 0.2)
    preds = [np.stack([det(GT1, 0.9), det(near_gt1, 0.8), det(GT2, 0.7)])]
    precision, recall, ap = precision_recall(preds, gts, 0.5)
    np.testing.assert_allclose(precision, [1.0, 0.5, 2.0 / 3.0])
    np.testing.assert_allclose(recall, [0.5, 0.5, 1.0])
    assert ap == pytest.approx((6 + 5 * 2.0 / 3.0) / 11.0)  # 28/33
    assert mean_average_precision(preds, gts, use_07_metric=False)[0.5] == pytest.approx(0.5 + 0.5 * 2.0 / 3.0)


def test_best_gt_already_matched_makes_a_false_positive_even_if_another_gt_overlaps():
    # DOTA rule: the detection only looks at its best-overlap GT. Shifts along the width (2 m):
    # IoU(d2, g1) = 1.7/2.3 = .74 (best, but g1 is taken), IoU(d2, g2) = 1.5/2.5 = .6 > .5.
    g1, g2 = np.array([0.0, 0.0, 2.0, 4.0, 0.0]), np.array([0.8, 0.0, 2.0, 4.0, 0.0])
    d2 = np.array([0.3, 0.0, 2.0, 4.0, 0.0])
    np.testing.assert_allclose(rotated_iou(d2[None], np.stack([g1, g2]))[0], [1.7 / 2.3, 0.6], atol=1e-6)
    precision, recall, ap = precision_recall([np.stack([det(g1, 0.9), det(d2, 0.8)])], [np.stack([g1, g2])], 0.5)
    np.testing.assert_allclose(recall, [0.5, 0.5])
    np.testing.assert_allclose(precision, [1.0, 0.5])
    assert ap == pytest.approx(6.0 / 11.0)


@pytest.mark.parametrize("yaw", YAWS)
@pytest.mark.parametrize("threshold", (0.3, 0.5, 0.7))
def test_match_just_above_and_just_below_each_threshold(yaw, threshold):
    gt = np.array([-12.0, 25.0, 2.1, 5.0, yaw])
    above = shifted_along_length(gt, shift_for_iou(gt[3], threshold + 0.01))
    below = shifted_along_length(gt, shift_for_iou(gt[3], threshold - 0.01))
    assert mean_average_precision([det(above, 0.6)[None]], [gt[None]], (threshold,))[threshold] == pytest.approx(1.0)
    assert mean_average_precision([det(below, 0.6)[None]], [gt[None]], (threshold,))[threshold] == 0.0
    # the lower thresholds still accept the "below" detection when they are far enough down
    result = mean_average_precision([det(below, 0.6)[None]], [gt[None]])
    assert result == {t: (1.0 if threshold - 0.01 > t else 0.0) for t in (0.3, 0.5, 0.7)}


def test_empty_frames_do_not_change_ap_but_predictions_on_them_are_false_positives():
    gts = [np.stack([GT1, GT2])]
    preds = [np.stack([det(GT1, 0.9), det(GT2, 0.5)])]
    base = mean_average_precision(preds, gts)
    padded = mean_average_precision([np.zeros((0, 6))] + preds + [np.zeros((0, 6))], [np.zeros((0, 5))] + gts + [[]])
    assert padded == base == {0.3: 1.0, 0.5: 1.0, 0.7: 1.0}
    # a confident detection on a frame without GT ranks first and is a false positive
    precision, recall, ap = precision_recall(preds + [det(GT1, 0.95)[None]], gts + [np.zeros((0, 5))], 0.5)
    np.testing.assert_allclose(precision, [0.0, 0.5, 2.0 / 3.0])
    np.testing.assert_allclose(recall, [0.0, 0.5, 1.0])
    assert ap == pytest.approx(2.0 / 3.0)  # every recall level's best precision is 2/3


def test_no_predictions_or_no_gt_give_zero():
    gts = [GT1[None], np.zeros((0, 5))]
    assert mean_average_precision([np.zeros((0, 6)), np.zeros((0, 6))], gts) == {0.3: 0.0, 0.5: 0.0, 0.7: 0.0}
    assert mean_average_precision([det(GT1, 0.9)[None], []], [np.zeros((0, 5)), []]) == {0.3: 0.0, 0.5: 0.0, 0.7: 0.0}
    assert mean_average_precision([], []) == {0.3: 0.0, 0.5: 0.0, 0.7: 0.0}
    precision, recall, ap = precision_recall([np.zeros((0, 6))], [GT1[None]], 0.5)
    assert precision.size == recall.size == 0 and ap == 0.0


def test_ranking_by_score_across_frames():
    gts = [GT1[None], np.zeros((0, 5))]
    false_first = [det(GT1, 0.5)[None], det(GT2, 0.9)[None]]
    true_first = [det(GT1, 0.9)[None], det(GT2, 0.5)[None]]
    assert mean_average_precision(false_first, gts)[0.5] == pytest.approx(0.5)  # precision .5 at recall 1
    assert mean_average_precision(true_first, gts)[0.5] == pytest.approx(1.0)
    precision, _, _ = precision_recall(false_first, gts, 0.5)
    np.testing.assert_allclose(precision, [0.0, 0.5])


def test_07_metric_and_all_point_differ_as_worked_out():
    # recall .5 .5 1 with precision 1 .5 2/3 (from the duplicate case): 28/33 vs 5/6
    recall, precision = np.array([0.5, 0.5, 1.0]), np.array([1.0, 0.5, 2.0 / 3.0])
    assert voc_ap(recall, precision, True) == pytest.approx(28.0 / 33.0)
    assert voc_ap(recall, precision, False) == pytest.approx(5.0 / 6.0)
    # recall .25 .5 with precision 1 1: 11-point sees t in {0,...,.5} -> 6/11; all-point 0.5
    assert voc_ap(np.array([0.25, 0.5]), np.ones(2), True) == pytest.approx(6.0 / 11.0)
    assert voc_ap(np.array([0.25, 0.5]), np.ones(2), False) == pytest.approx(0.5)


def test_bad_inputs_raise_clear_errors():
    with pytest.raises(ValueError, match="1 prediction frames but 2"):
        mean_average_precision([np.zeros((0, 6))], [np.zeros((0, 5))] * 2)
    with pytest.raises(ValueError, match=r"predictions\[0\].*NaN"):
        mean_average_precision([det(GT1, np.nan)[None]], [GT1[None]])
    with pytest.raises(ValueError, match=r"ground_truths\[0\]"):
        mean_average_precision([np.zeros((0, 6))], [np.zeros((1, 6))])
    with pytest.raises(ValueError, match="threshold"):
        mean_average_precision([det(GT1, 0.9)[None]], [GT1[None]], (1.0,))


def test_many_frames_are_evaluated():
    rng = np.random.default_rng(1)
    gts, preds = [], []
    for _ in range(500):
        frame_gt = np.column_stack([rng.uniform(-20, 20, (6, 2)), rng.uniform(1.5, 5, (6, 2)), rng.uniform(-3, 3, 6)])
        noisy = frame_gt + rng.normal(0, [0.3, 0.3, 0.1, 0.1, 0.05], frame_gt.shape)
        frame_pred = np.column_stack([noisy, rng.uniform(0.3, 1.0, 6)])
        gts.append(frame_gt)
        preds.append(frame_pred)
    result = mean_average_precision(preds, gts)
    assert 0.0 < result[0.7] < result[0.5] <= result[0.3] <= 1.0


# ---------------------------------------------------------------- end-point error
def test_end_point_error_hand_cases():
    gt = np.zeros((2, 2, 3))
    pred = gt.copy()
    pred[:, 0, 0] = (3.0, 4.0)  # error 5 in one of 6 cells
    assert end_point_error(pred, gt) == pytest.approx(5.0 / 6.0)
    mask = np.zeros((1, 2, 3))
    mask[0, 0, :2] = 1.0
    assert end_point_error(pred, gt, mask) == pytest.approx(2.5)
    assert end_point_error(gt, gt) == 0.0


def test_end_point_error_batched_with_broadcast_mask_and_accumulation():
    rng = np.random.default_rng(2)
    gt = rng.normal(size=(4, 3, 2, 5, 5))  # [B, T-1, 2, H, W]
    pred = gt + rng.normal(size=gt.shape)
    mask = (rng.uniform(size=(4, 1, 1, 5, 5)) > 0.5).astype(np.float32)  # broadcast over T-1
    norms = np.sqrt(((pred - gt) ** 2).sum(2))  # [B, T-1, H, W]
    selected = np.broadcast_to(mask[:, :, 0] > 0, norms.shape)
    assert end_point_error(pred, gt, mask) == pytest.approx(norms[selected].mean())
    total, count = end_point_error_terms(pred, gt, mask)
    assert count == selected.sum() and total == pytest.approx(norms[selected].sum())


def test_end_point_error_empty_mask_nan_and_errors():
    gt = np.zeros((2, 4, 4))
    pred = np.ones((2, 4, 4))
    assert np.isnan(end_point_error(pred, gt, np.zeros((1, 4, 4))))
    assert end_point_error_terms(pred, gt, np.zeros((1, 4, 4))) == (0.0, 0)
    pred[:, 0, 0] = np.nan
    mask = np.ones((1, 4, 4))
    mask[0, 0, 0] = 0.0
    assert end_point_error(pred, gt, mask) == pytest.approx(np.sqrt(2.0))  # NaN outside the mask is ignored
    with pytest.raises(ValueError, match="NaN"):
        end_point_error(pred, gt)
    with pytest.raises(ValueError, match="differs"):
        end_point_error(pred, gt[:, :3])
    with pytest.raises(ValueError, match=r"\[\.\.\., 2, H, W\]"):
        end_point_error(np.zeros((3, 4, 4)), np.zeros((3, 4, 4)))
    with pytest.raises(ValueError, match="broadcast"):
        end_point_error(gt, gt, np.ones((1, 3, 3)))


# ---------------------------------------------------------------- centre-distance matching
def test_centre_matching_recall_and_false_positives_per_frame() -> None:
    from rafd.eval.metrics import match_centres

    car = [1.0, 4.0, 0.0]  # width, length, yaw
    gts = [np.array([[0, 10, *car], [5, 20, *car]]), np.array([[0, 10, *car]]), np.zeros((0, 5))]
    preds = [
        np.array([[0.5, 10.5, *car, 0.9], [0.4, 10.4, *car, 0.8], [30, 30, *car, 0.7]]),  # hit, duplicate, FP
        np.array([[2.5, 10.0, *car, 0.6]]),  # 2.5 m away: a miss and a false positive
        np.array([[9, 9, *car, 0.5]]),  # FP in an empty frame
    ]
    matches = match_centres(preds, gts, max_distance=2.0)
    assert matches.true_positive.tolist() == [True, False, False, False, False]
    assert matches.num_gt == 3 and matches.num_frames == 3
    recall, fp_per_frame = matches.at_threshold(0.65)
    assert recall == pytest.approx(1 / 3) and fp_per_frame == pytest.approx(2 / 3)
    assert matches.at_threshold(0.0) == (pytest.approx(1 / 3), pytest.approx(4 / 3))
    recall, threshold = matches.recall_at_fp_rate(1.0)  # 3 false positives allowed in 3 frames
    assert recall == pytest.approx(1 / 3) and threshold == pytest.approx(0.6)
    assert match_centres(preds, gts, max_distance=3.0).true_positive.sum() == 2
    assert 0 < matches.average_precision() < 1

    # by range band: the vehicles at 10 m (two) and 20.6 m; the false positives at 10.4 m (the duplicate), 42.4 m,
    # 10.3 m and 12.7 m
    bands = matches.by_range(0.0, (0.0, 15.0, 25.0, 50.0))
    assert [b["vehicles"] for b in bands] == [2, 1, 0]
    assert [b["recall"] for b in bands[:2]] == [pytest.approx(50.0), 0.0] and np.isnan(bands[2]["recall"])
    assert [b["fp_per_frame"] for b in bands] == [pytest.approx(3 / 3), 0.0, pytest.approx(1 / 3)]
    assert [b["fp_per_frame"] for b in matches.by_range(0.65, (0.0, 15.0, 25.0, 50.0))] == [
        pytest.approx(1 / 3),
        0.0,
        pytest.approx(1 / 3),
    ]
