"""RaFD training losses: CenterNet focal heatmap loss, index-matched L1 box terms, L1 flow (paper 2.5)."""

from __future__ import annotations

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from rafd.train.config import LossConfig
from rafd.train.distill import heatmap_distillation

# The terms RaFDLoss returns, in a fixed order (the trainer stacks them into one tensor).
LOSS_TERMS = ("total", "det", "heatmap", "offset", "size", "rotation", "flow", "distill")


def focal_loss(
    logits: Tensor, target: Tensor, alpha: float = 2.0, beta: float = 4.0, negative_weight: Tensor | None = None
) -> Tensor:
    """CornerNet/CenterNet penalty-reduced focal loss: logits, target [B, 1, Hf, Wf] -> scalar.

    Positives are the cells where the Gaussian target is 1 (object centres); the sum over all
    cells is divided by the number of positives in the batch (at least 1), as in CenterNet.
    `negative_weight` [B, 1, Hf, Wf] (0 in the labeller's ignore regions) scales the negatives.
    """
    logits = logits.float()
    target = target.float()
    # log p and log(1 - p) from logits: exact where sigmoid saturates (CenterNet clamps instead).
    log_p = F.logsigmoid(logits)
    log_not_p = F.logsigmoid(-logits)
    p = torch.sigmoid(logits)
    positive = (target >= 1.0 - 1e-6).float()
    negative = 1.0 - positive
    positive_loss = -((1.0 - p) ** alpha) * log_p * positive
    negative_loss = -((1.0 - target) ** beta) * (p**alpha) * log_not_p * negative
    if negative_weight is not None:
        negative_loss = negative_loss * negative_weight.float()
    num_positive = positive.sum().clamp(min=1.0)
    return (positive_loss.sum() + negative_loss.sum()) / num_positive


def masked_l1(prediction: Tensor, target: Tensor, mask: Tensor) -> Tensor:
    """Mean L1 over real objects: prediction, target [B, K, D], mask [B, K] -> scalar.

    Padded slots contribute nothing; the sum is divided by the number of real entries (objects * D).
    """
    if prediction.shape != target.shape:
        raise ValueError(f"prediction {tuple(prediction.shape)} and target {tuple(target.shape)} differ")
    weight = mask.to(prediction.dtype)[..., None].expand_as(prediction)  # [B, K, D]
    total = (torch.abs(prediction - target) * weight).sum()
    return total / weight.sum().clamp(min=1.0)


def flow_l1(prediction: Tensor, target: Tensor, valid: Tensor) -> Tensor:
    """L1 flow loss over every consecutive pair: flows [B, P, 2, Hf, Wf], valid [B, P, 1, Hf, Wf] -> scalar.

    Per cell |dx| + |dy| (the l1 norm of the paper's L_f), averaged over cells with a defined target.
    """
    if prediction.shape != target.shape:
        raise ValueError(f"flow prediction {tuple(prediction.shape)} and target {tuple(target.shape)} differ")
    weight = valid.to(prediction.dtype)
    per_cell = torch.abs(prediction - target).sum(dim=2, keepdim=True)  # [B, P, 1, Hf, Wf]
    return (per_cell * weight).sum() / weight.sum().clamp(min=1.0)


class RaFDLoss(nn.Module):
    """Model outputs + batched targets -> dict of scalar loss terms ("total" = det + flow, + the heatmap distillation
    where the targets hold a teacher's heatmap: rafd.train.distill)."""

    def __init__(self, config: LossConfig | None = None) -> None:
        super().__init__()
        self.config = config or LossConfig()

    def forward(self, outputs: dict[str, Tensor], targets: dict[str, Tensor]) -> dict[str, Tensor]:
        cfg = self.config
        mask = targets["box_mask"]
        # Query slot m is GT object m (the model forces GT centres into the queries), so the box
        # terms compare slot by slot; K of the model and Kmax of the targets must agree.
        k = mask.shape[1]
        heatmap = focal_loss(
            outputs["heatmap"], targets["heatmap"], cfg.focal_alpha, cfg.focal_beta, targets.get("heatmap_weight")
        )
        offset = masked_l1(outputs["pred_offset"][:, :k].float(), targets["offset"], mask)
        size = masked_l1(outputs["pred_log_size"][:, :k].float(), targets["log_size"], mask)
        rotation = masked_l1(outputs["pred_rotation"][:, :k].float(), targets["rotation"], mask)
        det = (
            cfg.heatmap_weight * heatmap
            + cfg.offset_weight * offset
            + cfg.size_weight * size
            + cfg.rotation_weight * rotation
        )
        if "flow" in outputs and outputs["flow"] is not None and outputs["flow"].shape[1] > 0:
            flow = flow_l1(outputs["flow"].float(), targets["flow"], targets["flow_valid"])
        else:
            flow = heatmap.new_zeros(())
        if "teacher_heatmap" in targets:
            num_positive = (targets["heatmap"] >= 1.0 - 1e-6).sum().float()  # the focal loss's normaliser
            distill = heatmap_distillation(outputs["heatmap"], targets["teacher_heatmap"], num_positive)
        else:
            distill = heatmap.new_zeros(())
        # The flow term stays in the graph even at weight 0, so every parameter receives a
        # (zero) gradient and DDP does not see unused parameters.
        total = det + cfg.flow_weight * flow + cfg.distill_weight * distill
        return {
            "total": total,
            "det": det,
            "heatmap": heatmap,
            "offset": offset,
            "size": size,
            "rotation": rotation,
            "flow": flow,
            "distill": distill,
        }
