"""Single-level, single-head deformable attention (Deformable DETR's ms_deform_attn_core_pytorch idea).

Every query reads `num_points` bilinear samples of a value map around its reference point; the offsets
(in cells) and the softmax weights are predicted from the query. Locations are grid_sample
coordinates (x, y down) in [-1, 1], align_corners=False, zeros padding outside the map.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from rafd.model.attention import FeedForward


def deformable_sample(value: Tensor, locations: Tensor, weights: Tensor) -> Tensor:
    """value [B, C, H, W], locations [B, Q, P, 2] (normalised), weights [B, Q, P] -> [B, Q, C]."""
    sampled = F.grid_sample(value, locations, mode="bilinear", padding_mode="zeros", align_corners=False)  # [B, C, Q, P]
    out = (sampled * weights[:, None]).sum(dim=-1)  # [B, C, Q]
    return out.transpose(1, 2)  # [B, Q, C]


class DeformableAttention(nn.Module):
    """query [B, Q, C], reference [B, Q, 2] (normalised), value map [B, C, H, W] -> [B, Q, C]."""

    def __init__(self, channels: int, num_points: int, map_size: tuple[int, int]) -> None:
        super().__init__()
        self.num_points = num_points
        self.sampling_offsets = nn.Linear(channels, num_points * 2)
        self.attention_weights = nn.Linear(channels, num_points)
        self.value_proj = nn.Conv2d(channels, channels, 1)  # a Linear on every cell, applied to the map
        self.output_proj = nn.Linear(channels, channels)
        # One cell is 2 / W (x) and 2 / H (y) in normalised coordinates: offsets are predicted in cells.
        self.register_buffer(
            "cell", torch.tensor([2.0 / map_size[1], 2.0 / map_size[0]]), persistent=False
        )
        self._reset_parameters()

    def _reset_parameters(self) -> None:
        # Deformable DETR init: offsets start as a fixed pattern (here a ring of radius 1 cell around the
        # reference) and the weights uniform, so early training reads the neighbourhood evenly.
        nn.init.zeros_(self.sampling_offsets.weight)
        angles = torch.arange(self.num_points, dtype=torch.float32) * (2.0 * math.pi / self.num_points)
        with torch.no_grad():
            self.sampling_offsets.bias.copy_(torch.stack([angles.cos(), angles.sin()], -1).flatten())
        nn.init.zeros_(self.attention_weights.weight)
        nn.init.zeros_(self.attention_weights.bias)
        nn.init.xavier_uniform_(self.value_proj.weight)
        nn.init.zeros_(self.value_proj.bias)
        nn.init.xavier_uniform_(self.output_proj.weight)
        nn.init.zeros_(self.output_proj.bias)

    def forward(self, query: Tensor, reference: Tensor, value: Tensor) -> Tensor:
        batch, num_queries, _ = query.shape
        offsets = self.sampling_offsets(query).reshape(batch, num_queries, self.num_points, 2)  # [B, Q, P, 2] cells
        locations = reference[:, :, None, :] + offsets * self.cell  # [B, Q, P, 2]
        weights = self.attention_weights(query).softmax(dim=-1)  # [B, Q, P]
        out = deformable_sample(self.value_proj(value), locations, weights)  # [B, Q, C]
        return self.output_proj(out)


class DeformableLayer(nn.Module):
    """Post-norm deformable cross-attention + FFN: query [B, Q, C] -> [B, Q, C]."""

    def __init__(self, attention: DeformableAttention, channels: int, ffn_ratio: int) -> None:
        super().__init__()
        self.attention = attention
        self.norm1 = nn.LayerNorm(channels)
        self.ffn = FeedForward(channels, ffn_ratio)
        self.norm2 = nn.LayerNorm(channels)

    def forward(self, query: Tensor, reference: Tensor, value: Tensor) -> Tensor:
        x = self.norm1(query + self.attention(query, reference, value))
        return self.norm2(x + self.ffn(x))
