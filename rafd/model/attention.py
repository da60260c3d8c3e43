"""Single-head attention building blocks shared by enhancement, flow and the decoder."""

from __future__ import annotations

import math
from collections.abc import Callable

from torch import Tensor, nn

# (q [B, N, C], k [B, M, C], v [B, M, C]) -> [B, N, C]; windowed variants plug in here.
AttentionFn = Callable[[Tensor, Tensor, Tensor], Tensor]


def single_head_attention(query: Tensor, key: Tensor, value: Tensor) -> Tensor:
    """Global scaled dot-product attention: q [B, N, C], k/v [B, M, C] -> [B, N, C]."""
    # scale the [B, N, C] query, not the [B, N, M] scores: M/C times less work on big maps
    scores = (query / math.sqrt(query.shape[-1])) @ key.transpose(1, 2)  # [B, N, M]
    return scores.softmax(dim=-1) @ value  # [B, N, C]


class FeedForward(nn.Module):
    """Position-wise MLP: [..., C] -> [..., C] through C * ratio hidden units."""

    def __init__(self, channels: int, ratio: int) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Linear(channels, channels * ratio), nn.GELU(), nn.Linear(channels * ratio, channels)
        )

    def forward(self, x: Tensor) -> Tensor:
        return self.net(x)


class AttentionLayer(nn.Module):
    """Post-norm single-head attention (+ FFN when ffn_ratio > 0): x [B, N, C], source [B, M, C] -> [B, N, C].

    source=None is self-attention. `attention` swaps the global attention for a windowed one
    (GMFlow style: projections on the whole map, only the softmax is split into windows).
    """

    def __init__(self, channels: int, ffn_ratio: int) -> None:
        super().__init__()
        self.q_proj = nn.Linear(channels, channels, bias=False)
        self.k_proj = nn.Linear(channels, channels, bias=False)
        self.v_proj = nn.Linear(channels, channels, bias=False)
        self.out_proj = nn.Linear(channels, channels)
        self.norm1 = nn.LayerNorm(channels)
        self.ffn = FeedForward(channels, ffn_ratio) if ffn_ratio > 0 else None
        self.norm2 = nn.LayerNorm(channels) if ffn_ratio > 0 else None

    def forward(
        self, x: Tensor, source: Tensor | None = None, attention: AttentionFn = single_head_attention
    ) -> Tensor:
        source = x if source is None else source
        message = attention(self.q_proj(x), self.k_proj(source), self.v_proj(source))  # [B, N, C]
        x = self.norm1(x + self.out_proj(message))
        if self.ffn is not None and self.norm2 is not None:  # both or neither
            x = self.norm2(x + self.ffn(x))
        return x
