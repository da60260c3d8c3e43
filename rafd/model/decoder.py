"""DETR-style query decoder (CenterFormer): self-attention over the peak queries, deformable
cross-attention into the final BEV map around each peak, FFN; then the box regression heads."""

from __future__ import annotations

import math
from typing import cast

from torch import Tensor, nn

from rafd.model.attention import AttentionLayer
from rafd.model.deformable import DeformableLayer


class DecoderLayer(nn.Module):
    """queries [B, K, C], reference [B, K, 2] normalised, value map [B, C, Hf, Wf] -> [B, K, C]."""

    def __init__(self, self_attention: AttentionLayer, cross_attention: DeformableLayer) -> None:
        super().__init__()
        self.self_attention = self_attention  # no FFN of its own: the cross-attention layer carries it
        self.cross_attention = cross_attention

    def forward(self, queries: Tensor, reference: Tensor, value: Tensor) -> Tensor:
        # Self-attention lets neighbouring peaks suppress duplicates / share context (DETR).
        queries = self.self_attention(queries)
        return self.cross_attention(queries, reference, value)


class QueryDecoder(nn.Module):
    """Stack of DecoderLayers: [B, K, C] -> [B, K, C]."""

    def __init__(self, layers: list[DecoderLayer]) -> None:
        super().__init__()
        self.layers = nn.ModuleList(layers)

    def forward(self, queries: Tensor, reference: Tensor, value: Tensor) -> Tensor:
        for layer in self.layers:
            queries = layer(queries, reference, value)
        return queries


def mlp(channels: int, out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(channels, channels), nn.ReLU(inplace=True), nn.Linear(channels, out))


class BoxRegression(nn.Module):
    """queries [B, K, C] -> offset [B, K, 2] cells, log_size [B, K, 2], rotation [B, K, 2] (sin, cos)."""

    def __init__(self, channels: int, initial_size: float = 3.0) -> None:
        super().__init__()
        self.offset = mlp(channels, 2)
        self.log_size = mlp(channels, 2)
        self.rotation = mlp(channels, 2)
        # Start at a vehicle-sized box (log 3 m) rather than 1 m: the L1 size loss starts smaller.
        nn.init.constant_(cast(nn.Linear, self.log_size[-1]).bias, math.log(initial_size))

    def forward(self, queries: Tensor) -> dict[str, Tensor]:
        return {
            "pred_offset": self.offset(queries),
            "pred_log_size": self.log_size(queries),
            "pred_rotation": self.rotation(queries),
        }
