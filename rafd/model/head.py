"""Centre heatmap head + top-K peak queries (CenterFormer) + decoder -> per-query boxes and scores."""

from __future__ import annotations

from typing import cast

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from rafd.model.boxes import decode_boxes
from rafd.model.decoder import BoxRegression, QueryDecoder

# CenterNet's focal-loss prior: sigmoid(-2.19) = 0.1, so the background loss does not explode at start.
HEATMAP_PRIOR_BIAS = -2.19


class HeatmapHead(nn.Module):
    """[B, C, Hf, Wf] -> [B, num_classes, Hf, Wf] centre logits."""

    def __init__(self, channels: int, num_classes: int) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv2d(channels, channels, 3, padding=1), nn.ReLU(inplace=True), nn.Conv2d(channels, num_classes, 1)
        )
        nn.init.constant_(cast(Tensor, self.net[-1].bias), HEATMAP_PRIOR_BIAS)  # the last Conv2d's (bias=True)

    def forward(self, features: Tensor) -> Tensor:
        return self.net(features)


def best_class(heatmap: Tensor) -> Tensor:
    """[B, Ncls, Hf, Wf] -> [B, 1, Hf, Wf] best class logit per cell (a no-op for the one-class benchmark)."""
    return heatmap if heatmap.shape[1] == 1 else heatmap.amax(dim=1, keepdim=True)


def peak_indices(heatmap: Tensor, k: int) -> Tensor:
    """Top-k local maxima after 3x3 max-pool NMS: [B, Ncls, Hf, Wf] logits -> [B, k] int64 flat cell indices."""
    logits = best_class(heatmap.detach())  # [B, 1, Hf, Wf]
    pooled = F.max_pool2d(logits, 3, stride=1, padding=1)  # [B, 1, Hf, Wf]
    # Non-maxima are ranked below every maximum instead of being removed (static shape for ONNX),
    # but still by their own score: a constant fill would tie them, and ORT and torch break ties
    # differently when a heatmap has fewer than k maxima.
    is_peak = (pooled == logits).to(logits.dtype)
    key = torch.sigmoid(logits) + is_peak  # maxima in [1, 2], the rest in [0, 1]
    return key.flatten(1).topk(k, dim=1).indices  # [B, k]


def force_ground_truth(peaks: Tensor, gt_indices: Tensor, gt_mask: Tensor) -> Tensor:
    """Slot m = GT m wherever gt_mask[:, m] > 0, else the m-th peak: [B, K] x [B, Kg] -> [B, K] (Kg <= K)."""
    batch, k = peaks.shape
    missing = k - gt_indices.shape[1]
    if missing < 0:
        raise ValueError(f"{gt_indices.shape[1]} GT slots do not fit in {k} queries")
    if missing:  # fewer GT slots than queries: the rest are peaks
        gt_indices = torch.cat([gt_indices, gt_indices.new_zeros(batch, missing)], dim=1)
        gt_mask = torch.cat([gt_mask, gt_mask.new_zeros(batch, missing)], dim=1)
    return torch.where(gt_mask > 0, gt_indices.to(peaks.dtype), peaks)


def gather_cells(features: Tensor, indices: Tensor) -> Tensor:
    """features [B, N, D], indices [B, K] -> [B, K, D]."""
    return torch.gather(features, 1, indices[..., None].expand(-1, -1, features.shape[-1]))


class DetectionHead(nn.Module):
    """T_T [B, C, Hf, Wf] (+ optional GT indices) -> heatmap, query indices, regression, scores, boxes."""

    # buffers (register_buffer in __init__), declared so that type checkers know them as tensors
    centres: Tensor
    grid: Tensor

    def __init__(
        self,
        heatmap: HeatmapHead,
        position_embedding: nn.Linear,
        decoder: QueryDecoder,
        regression: BoxRegression,
        num_queries: int,
        centres: Tensor,
        grid: Tensor,
        cell_size: float,
        box_encoding: str,
    ) -> None:
        super().__init__()
        self.heatmap = heatmap
        self.position_embedding = position_embedding  # Linear(2 -> C) of the normalised cell position
        self.decoder = decoder
        self.regression = regression
        self.num_queries = num_queries
        self.cell_size = cell_size
        self.box_encoding = box_encoding  # rafd.config.HeadConfig.box_encoding
        self.register_buffer("centres", centres, persistent=False)  # [Hf*Wf, 2] metres
        self.register_buffer("grid", grid, persistent=False)  # [Hf*Wf, 2] normalised (x, y down)

    def forward(
        self, features: Tensor, gt_indices: Tensor | None = None, gt_mask: Tensor | None = None
    ) -> dict[str, Tensor]:
        batch = features.shape[0]
        heatmap = self.heatmap(features)  # [B, Ncls, Hf, Wf]
        indices = peak_indices(heatmap, self.num_queries)  # [B, K]
        if gt_indices is not None and gt_mask is not None:
            indices = force_ground_truth(indices, gt_indices, gt_mask)
        cells = features.flatten(2).transpose(1, 2)  # [B, Hf*Wf, C]
        grid = self.grid.to(features.dtype)[None].expand(batch, -1, -1)  # [B, Hf*Wf, 2]
        reference = gather_cells(grid, indices)  # [B, K, 2]
        queries = gather_cells(cells, indices) + self.position_embedding(reference)  # [B, K, C]
        queries = self.decoder(queries, reference, features)  # [B, K, C]
        outputs = self.regression(queries)
        logits = best_class(heatmap).flatten(1)  # [B, Hf*Wf]
        centres = gather_cells(self.centres.to(features.dtype)[None].expand(batch, -1, -1), indices)  # [B, K, 2]
        outputs.update(
            heatmap=heatmap,
            query_indices=indices,
            scores=torch.sigmoid(torch.gather(logits, 1, indices)),  # [B, K]
            boxes=decode_boxes(
                centres,
                outputs["pred_offset"],
                outputs["pred_log_size"],
                outputs["pred_rotation"],
                self.cell_size,
                self.box_encoding,
            ),
        )
        return outputs
