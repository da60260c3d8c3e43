"""Single-level, single-head deformable attention (Deformable DETR's ms_deform_attn_core_pytorch idea).

Every query reads `num_points` bilinear samples of a value map around its reference point; the offsets
(in cells) and the softmax weights are predicted from the query. Locations are grid_sample
coordinates (x, y down) in [-1, 1], align_corners=False, zeros padding outside the map.

Two layouts of the same mathematics: token-major (queries [B, Q, C], the decoder's few peak queries) and
channel-major maps (queries = every cell of a [B, C, H, W] map, the propagation's case): there every Linear
is applied as a 1x1 convolution and LayerNorm normalises over the channel axis, so the map is never
transposed, GridSample writes [B, C, P, Q] and the point weighting reduces over the P axis of whole
contiguous rows of queries (sampling and weighting fused into one pass over the samples).
"""

from __future__ import annotations

import math
from typing import cast

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from rafd.model.attention import FeedForward


def deformable_sample(value: Tensor, locations: Tensor, weights: Tensor) -> Tensor:
    """value [B, C, H, W], locations [B, Q, P, 2] (normalised), weights [B, Q, P] -> [B, Q, C]."""
    sampled = F.grid_sample(
        value, locations, mode="bilinear", padding_mode="zeros", align_corners=False
    )  # [B, C, Q, P]
    out = (sampled * weights[:, None]).sum(dim=-1)  # [B, C, Q]
    return out.transpose(1, 2)  # [B, Q, C]


def deformable_sample_points_major(value: Tensor, locations: Tensor, weights: Tensor) -> Tensor:
    """value [B, C, H, W], locations [B, P, Q, 2] (normalised), weights [B, P, Q] -> [B, C, Q] (channel-major)."""
    sampled = F.grid_sample(
        value, locations, mode="bilinear", padding_mode="zeros", align_corners=False
    )  # [B, C, P, Q]
    weighted = sampled * weights[:, None]  # [B, C, P, Q]
    # a chain of adds of the P point planes, not ReduceSum: runtimes fuse the adds into one element-wise pass
    # (OpenVINO's ReduceSum over this axis took ~4 ms per call on the paper map, the adds a fraction of it)
    out = weighted[:, :, 0]
    for point in range(1, weighted.shape[2]):
        out = out + weighted[:, :, point]
    return out  # [B, C, Q]


def linear_on_map(linear: nn.Linear, x: Tensor) -> Tensor:
    """A Linear applied to every cell of a channel-major map: [B, C_in, H, W] -> [B, C_out, H, W] (a 1x1 conv)."""
    return F.conv2d(x, linear.weight[:, :, None, None], linear.bias)


def layer_norm_on_map(norm: nn.LayerNorm, x: Tensor) -> Tensor:
    """nn.LayerNorm over the channels of every cell of [B, C, H, W] (the same statistics, eps and affine)."""
    mean = x.mean(dim=1, keepdim=True)  # [B, 1, H, W]
    centred = x - mean
    variance = centred.square().mean(dim=1, keepdim=True)  # biased, as nn.LayerNorm
    normalised = centred * torch.rsqrt(variance + norm.eps)
    return normalised * norm.weight[:, None, None] + norm.bias[:, None, None]


class DeformableAttention(nn.Module):
    """query [B, Q, C], reference [B, Q, 2] (normalised), value map [B, C, H, W] -> [B, Q, C]."""

    cell: Tensor  # a buffer (register_buffer in __init__), declared so that type checkers know it as a tensor

    def __init__(self, channels: int, num_points: int, map_size: tuple[int, int]) -> None:
        super().__init__()
        self.num_points = num_points
        self.sampling_offsets = nn.Linear(channels, num_points * 2)
        self.attention_weights = nn.Linear(channels, num_points)
        self.value_proj = nn.Conv2d(channels, channels, 1)  # a Linear on every cell, applied to the map
        self.output_proj = nn.Linear(channels, channels)
        # One cell is 2 / W (x) and 2 / H (y) in normalised coordinates: offsets are predicted in cells.
        self.register_buffer("cell", torch.tensor([2.0 / map_size[1], 2.0 / map_size[0]]), persistent=False)
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
        nn.init.zeros_(cast(Tensor, self.value_proj.bias))  # Conv2d(bias=True): never None
        nn.init.xavier_uniform_(self.output_proj.weight)
        nn.init.zeros_(self.output_proj.bias)

    def forward(self, query: Tensor, reference: Tensor, value: Tensor) -> Tensor:
        if query.dim() == 4:  # a query map: forward_map, through the call so the exported nodes get this scope
            return self.forward_map(query, reference, value)
        batch, num_queries, _ = query.shape
        offsets = self.sampling_offsets(query).reshape(batch, num_queries, self.num_points, 2)  # [B, Q, P, 2] cells
        locations = reference[:, :, None, :] + offsets * self.cell  # [B, Q, P, 2]
        weights = self.attention_weights(query).softmax(dim=-1)  # [B, Q, P]
        out = deformable_sample(self.value_proj(value), locations, weights)  # [B, Q, C]
        return self.output_proj(out)

    def forward_map(self, query: Tensor, reference: Tensor, value: Tensor) -> Tensor:
        """forward for every cell of a query map: query [B, C, H, W], reference [B, H*W, 2] -> [B, C, H, W]."""
        batch, channels, height, width = query.shape
        offsets = linear_on_map(self.sampling_offsets, query)  # [B, P*2, H, W] cells, channel = p * 2 + xy
        offsets = offsets.reshape(batch, self.num_points, 2, height * width).transpose(2, 3)  # [B, P, Q, 2] (small)
        locations = reference[:, None] + offsets * self.cell  # [B, P, Q, 2]
        weights = linear_on_map(self.attention_weights, query).flatten(2).softmax(dim=1)  # [B, P, Q]
        out = deformable_sample_points_major(self.value_proj(value), locations, weights)  # [B, C, Q]
        return linear_on_map(self.output_proj, out.reshape(batch, channels, height, width))  # [B, C, H, W]


class DeformableLayer(nn.Module):
    """Deformable cross-attention + FFN, each a residual branch: query [B, Q, C] -> [B, Q, C].

    norm "post" (Deformable DETR): x = LN(q + attn(q)), out = LN(x + ffn(x)); every output cell is normalised.
    norm "pre": x = q + attn(LN(q)), out = x + ffn(LN(x)), with both branches' last projections zero-initialised,
    so a fresh layer is the identity: the query map (a frame's features) passes unchanged until the branch learns
    what to add, and a head trained on single-frame features reads the same features under a multi-frame model.
    """

    def __init__(self, attention: DeformableAttention, channels: int, ffn_ratio: int, norm: str = "post") -> None:
        super().__init__()
        if norm not in ("post", "pre"):
            raise ValueError(f"norm must be 'post' or 'pre', got {norm!r}")
        self.attention = attention
        self.norm1 = nn.LayerNorm(channels)
        self.ffn = FeedForward(channels, ffn_ratio)
        self.norm2 = nn.LayerNorm(channels)
        self.pre_norm = norm == "pre"
        if self.pre_norm:
            for last in (attention.output_proj, cast(nn.Linear, self.ffn.net[-1])):
                nn.init.zeros_(last.weight)
                nn.init.zeros_(last.bias)

    def forward(self, query: Tensor, reference: Tensor, value: Tensor) -> Tensor:
        """Token-major queries [B, Q, C]; a query map [B, C, H, W] goes to forward_map (called through the module,
        a propagation's layer gets its own scope, /propagation/layers.0/..., in the exported graph)."""
        if query.dim() == 4:
            return self.forward_map(query, reference, value)
        if self.pre_norm:
            x = query + self.attention(self.norm1(query), reference, value)
            return x + self.ffn(self.norm2(x))
        x = self.norm1(query + self.attention(query, reference, value))
        return self.norm2(x + self.ffn(x))

    def forward_map(self, query: Tensor, reference: Tensor, value: Tensor) -> Tensor:
        """forward for every cell of a channel-major query map: [B, C, H, W] -> [B, C, H, W]."""
        hidden, activation, out = cast("tuple[nn.Linear, nn.GELU, nn.Linear]", self.ffn.net)  # FeedForward's layers

        def ffn(x: Tensor) -> Tensor:
            return linear_on_map(out, activation(linear_on_map(hidden, x)))

        if self.pre_norm:
            x = query + self.attention(layer_norm_on_map(self.norm1, query), reference, value)  # forward_map
            return x + ffn(layer_norm_on_map(self.norm2, x))
        x = layer_norm_on_map(self.norm1, query + self.attention(query, reference, value))  # forward_map
        return layer_norm_on_map(self.norm2, x + ffn(x))
