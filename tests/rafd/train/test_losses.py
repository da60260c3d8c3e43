"""Loss terms checked by hand on tiny tensors."""

from __future__ import annotations

import math

import pytest
import torch

from rafd.train.config import LossConfig
from rafd.train.losses import RaFDLoss, flow_l1, focal_loss, masked_l1


def test_focal_loss_matches_hand_computation() -> None:
    # p = sigmoid(0) = 0.5 everywhere; one positive (target 1), one near negative (0.5), one far (0).
    logits = torch.zeros(1, 1, 1, 3)
    target = torch.tensor([1.0, 0.5, 0.0]).reshape(1, 1, 1, 3)
    positive = -(0.5**2) * math.log(0.5)
    near = -((1 - 0.5) ** 4) * (0.5**2) * math.log(0.5)
    far = -(1.0**4) * (0.5**2) * math.log(0.5)
    expected = (positive + near + far) / 1  # one positive
    assert focal_loss(logits, target).item() == pytest.approx(expected, rel=1e-6)


def test_focal_loss_normalises_by_number_of_objects() -> None:
    logits = torch.tensor([[2.0, -1.0, 0.5, -3.0]]).reshape(1, 1, 2, 2)
    target = torch.tensor([[1.0, 0.0, 1.0, 0.3]]).reshape(1, 1, 2, 2)
    p = torch.sigmoid(logits).flatten().tolist()
    pos = [-((1 - p[0]) ** 2) * math.log(p[0]), -((1 - p[2]) ** 2) * math.log(p[2])]
    neg = [-(1.0**4) * p[1] ** 2 * math.log(1 - p[1]), -((1 - 0.3) ** 4) * p[3] ** 2 * math.log(1 - p[3])]
    assert focal_loss(logits, target).item() == pytest.approx((sum(pos) + sum(neg)) / 2, rel=1e-5)
    # Confident and right -> small; confident and wrong -> large.
    assert (
        focal_loss(torch.tensor([8.0, -8.0]).reshape(1, 1, 1, 2), torch.tensor([1.0, 0.0]).reshape(1, 1, 1, 2)) < 1e-3
    )
    assert focal_loss(torch.tensor([-8.0, 8.0]).reshape(1, 1, 1, 2), torch.tensor([1.0, 0.0]).reshape(1, 1, 1, 2)) > 10


def test_masked_l1_ignores_padding() -> None:
    prediction = torch.tensor([[[1.0, 2.0], [100.0, -100.0]]])  # second slot is padding
    target = torch.tensor([[[0.0, 4.0], [0.0, 0.0]]])
    mask = torch.tensor([[1.0, 0.0]])
    # (|1 - 0| + |2 - 4|) / 2 entries
    assert masked_l1(prediction, target, mask).item() == pytest.approx(1.5)
    assert masked_l1(prediction, target, torch.zeros(1, 2)).item() == 0.0


def test_flow_loss_ignores_invalid_cells() -> None:
    prediction = torch.zeros(1, 2, 2, 1, 2)  # [B, pairs, 2, Hf, Wf]
    target = torch.zeros(1, 2, 2, 1, 2)
    target[0, 0, :, 0, 0] = torch.tensor([1.0, -2.0])  # valid cell: |1| + |-2| = 3
    target[0, 1, :, 0, 1] = torch.tensor([50.0, 50.0])  # invalid cell: must not count
    valid = torch.ones(1, 2, 1, 1, 2)
    valid[0, 1, 0, 0, 1] = 0.0
    # 3 valid cells per... pair 0: 2 valid cells, pair 1: 1 valid cell -> 3 cells, error 3 in total
    assert flow_l1(prediction, target, valid).item() == pytest.approx(3.0 / 3)


def _outputs_and_targets(num_pairs: int) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
    generator = torch.Generator().manual_seed(0)
    outputs = {
        "heatmap": torch.randn(2, 1, 4, 4, generator=generator),
        "pred_offset": torch.randn(2, 3, 2, generator=generator),
        "pred_log_size": torch.randn(2, 3, 2, generator=generator),
        "pred_rotation": torch.randn(2, 3, 2, generator=generator),
    }
    heatmap = torch.zeros(2, 1, 4, 4)
    heatmap[0, 0, 1, 1] = 1.0
    targets = {
        "heatmap": heatmap,
        "offset": torch.zeros(2, 3, 2),
        "log_size": torch.zeros(2, 3, 2),
        "rotation": torch.zeros(2, 3, 2),
        "box_mask": torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]),
        "flow": torch.ones(2, num_pairs, 2, 4, 4),
        "flow_valid": torch.ones(2, num_pairs, 1, 4, 4),
    }
    if num_pairs:
        outputs["flow"] = torch.zeros(2, num_pairs, 2, 4, 4, requires_grad=True)
    return outputs, targets


def test_total_is_weighted_sum_and_flow_weight_zero_disables_flow() -> None:
    outputs, targets = _outputs_and_targets(num_pairs=3)
    terms = RaFDLoss(LossConfig(size_weight=0.5))(outputs, targets)
    det = terms["heatmap"] + terms["offset"] + 0.5 * terms["size"] + terms["rotation"]
    assert terms["det"].item() == pytest.approx(det.item(), rel=1e-6)
    assert terms["flow"].item() == pytest.approx(2.0)  # |0 - 1| + |0 - 1| per cell
    assert terms["total"].item() == pytest.approx(det.item() + 2.0, rel=1e-6)
    no_flow = RaFDLoss(LossConfig(flow_weight=0.0))(outputs, targets)
    assert no_flow["total"].item() == pytest.approx(no_flow["det"].item())
    no_flow["total"].backward()
    assert outputs["flow"].grad is not None and torch.all(outputs["flow"].grad == 0)


def test_single_frame_has_zero_flow_term() -> None:
    outputs, targets = _outputs_and_targets(num_pairs=0)
    terms = RaFDLoss()(outputs, targets)
    assert terms["flow"].item() == 0.0
    assert set(terms) == {"total", "det", "heatmap", "offset", "size", "rotation", "flow", "distill"}
    assert terms["distill"].item() == 0.0  # no teacher
