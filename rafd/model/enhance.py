"""Feature enhancement (paper 2.1): blocks of regular + shifted window single-head self-attention.

Windows are Hf/2 x Wf/2 (2 x 2 windows, the paper) or, as a speed option, any even side that divides the
map; the shifted layer rolls the map by half a window and masks attention between pieces that the roll
wrapped together (Swin), as GMFlow's single_head_split_window_attention does. The mask depends only on the
static map size and window: a buffer.
"""

from __future__ import annotations

import math
from functools import partial
from typing import cast

import torch
from torch import Tensor, nn

from rafd.model.attention import AttentionLayer

MASKED = -1.0e4  # additive logit for forbidden pairs: exp(-1e4) == 0 in fp32, still finite in fp16


def window_partition(x: Tensor, window: tuple[int, int]) -> Tensor:
    """[B, H, W, C] -> [B * nW, wh * ww, C], windows in row-major order."""
    batch, height, width, channels = x.shape
    wh, ww = window
    x = x.reshape(batch, height // wh, wh, width // ww, ww, channels)  # [B, nH, wh, nW, ww, C]
    return x.permute(0, 1, 3, 2, 4, 5).reshape(-1, wh * ww, channels)  # [B*nH*nW, wh*ww, C]


def window_merge(x: Tensor, batch: int, height: int, width: int, window: tuple[int, int]) -> Tensor:
    """[B * nW, wh * ww, C] -> [B, H, W, C] (inverse of window_partition)."""
    wh, ww = window
    channels = x.shape[-1]
    x = x.reshape(batch, height // wh, width // ww, wh, ww, channels)  # [B, nH, nW, wh, ww, C]
    return x.permute(0, 1, 3, 2, 4, 5).reshape(batch, height, width, channels)  # [B, H, W, C]


def shifted_window_mask(height: int, width: int, window: tuple[int, int], shift: tuple[int, int]) -> Tensor:
    """-> [nW, wh*ww, wh*ww] additive mask: 0 where two tokens came from the same region before the roll."""
    labels = torch.zeros(1, height, width, 1)
    region = 0
    for rows in (slice(0, -window[0]), slice(-window[0], -shift[0]), slice(-shift[0], None)):
        for cols in (slice(0, -window[1]), slice(-window[1], -shift[1]), slice(-shift[1], None)):
            labels[:, rows, cols, :] = region
            region += 1
    labels = window_partition(labels, window).squeeze(-1)  # [nW, wh*ww]
    different = labels[:, :, None] != labels[:, None, :]  # [nW, N, N]
    return torch.where(different, torch.tensor(MASKED), torch.tensor(0.0))


def window_attention(
    query: Tensor,
    key: Tensor,
    value: Tensor,
    size: tuple[int, int],
    window: tuple[int, int],
    shift: tuple[int, int] = (0, 0),
    mask: Tensor | None = None,
) -> Tensor:
    """Single-head attention inside windows: q/k/v [B, H*W, C] -> [B, H*W, C]."""
    batch, _, channels = query.shape
    height, width = size
    wh, ww = window

    def split(x: Tensor) -> Tensor:
        x = x.reshape(batch, height, width, channels)  # [B, H, W, C]
        if shift != (0, 0):
            x = torch.roll(x, shifts=(-shift[0], -shift[1]), dims=(1, 2))
        return window_partition(x, window)  # [B*nW, N, C]

    q, k, v = split(query), split(key), split(value)
    scores = (q / math.sqrt(channels)) @ k.transpose(1, 2)  # [B*nW, N, N] (scaling q is cheaper)
    if mask is not None:
        num_windows = mask.shape[0]
        scores = scores.reshape(batch, num_windows, wh * ww, wh * ww) + mask[None]  # [B, nW, N, N]
        scores = scores.reshape(batch * num_windows, wh * ww, wh * ww)  # [B*nW, N, N]
    out = window_merge(scores.softmax(dim=-1) @ v, batch, height, width, window)  # [B, H, W, C]
    if shift != (0, 0):
        out = torch.roll(out, shifts=shift, dims=(1, 2))
    return out.reshape(batch, height * width, channels)  # [B, H*W, C]


class WindowBlock(nn.Module):
    """Regular-window layer then shifted-window layer: [B, H*W, C] -> [B, H*W, C].

    window: (wh, ww) cells, default half the map (2 x 2 windows, the paper); each side must divide the map.
    """

    mask: Tensor  # a buffer (register_buffer in __init__), declared so that type checkers know it as a tensor

    def __init__(
        self,
        regular: AttentionLayer,
        shifted: AttentionLayer,
        size: tuple[int, int],
        window: tuple[int, int] | None = None,
    ) -> None:
        super().__init__()
        self.regular, self.shifted = regular, shifted
        self.size = size
        self.window = window or (size[0] // 2, size[1] // 2)
        if size[0] % self.window[0] or size[1] % self.window[1]:
            raise ValueError(f"window {self.window} does not tile the {size} map")
        self.shift = (self.window[0] // 2, self.window[1] // 2)
        # Derived from the static map size, not learned: kept out of the state dict.
        self.register_buffer("mask", shifted_window_mask(size[0], size[1], self.window, self.shift), persistent=False)

    def forward(self, x: Tensor) -> Tensor:
        x = self.regular(x, attention=partial(window_attention, size=self.size, window=self.window))
        shifted = partial(window_attention, size=self.size, window=self.window, shift=self.shift, mask=self.mask)
        return self.shifted(x, attention=shifted)


class FeatureEnhancement(nn.Module):
    """[B, C, Hf, Wf] -> [B, C, Hf, Wf] with spatial context; no blocks = identity (ablation)."""

    def __init__(self, blocks: list[WindowBlock]) -> None:
        super().__init__()
        self.blocks = nn.ModuleList(blocks)

    def forward(self, features: Tensor) -> Tensor:
        if len(self.blocks) == 0:
            return features
        batch, channels, height, width = features.shape
        x = features.flatten(2).transpose(1, 2)  # [B, Hf*Wf, C]
        for block in self.blocks:
            x = block(x)
        return x.transpose(1, 2).reshape(batch, channels, height, width)  # [B, C, Hf, Wf]


class ConvBlock(nn.Module):
    """Residual block of two 3x3 conv + BN, the second dilated by 2 (a 7 x 7 cell context per block):
    [B, C, H, W] -> [B, C, H, W]. The CPU recipe's enhancement: two large operations per block where a window
    attention block runs dozens of small ones; its last BN scale starts at zero, so a block starts as the identity."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.conv1 = nn.Sequential(nn.Conv2d(channels, channels, 3, padding=1, bias=False), nn.BatchNorm2d(channels))
        self.conv2 = nn.Sequential(
            nn.Conv2d(channels, channels, 3, padding=2, dilation=2, bias=False), nn.BatchNorm2d(channels)
        )
        nn.init.zeros_(cast(nn.BatchNorm2d, self.conv2[1]).weight)  # (Conv2d, BatchNorm2d)

    def forward(self, x: Tensor) -> Tensor:
        return torch.relu(x + self.conv2(torch.relu(self.conv1(x))))


class ConvEnhancement(nn.Module):
    """[B, C, Hf, Wf] -> [B, C, Hf, Wf]: ConvBlocks on the channel-major map (no transposes)."""

    def __init__(self, blocks: list[ConvBlock]) -> None:
        super().__init__()
        self.blocks = nn.Sequential(*blocks)

    def forward(self, features: Tensor) -> Tensor:
        return self.blocks(features)


def build_enhancement(
    channels: int,
    feature_size: int,
    num_blocks: int,
    ffn_ratio: int,
    enabled: bool,
    window: int = 0,
    kind: str = "window_attention",
) -> nn.Module:
    """window: side in cells, 0 = half the map (the paper); kind: rafd.config.EnhanceConfig.kind."""
    if kind == "conv":
        return ConvEnhancement([ConvBlock(channels) for _ in range(num_blocks if enabled else 0)])
    size = (feature_size, feature_size)
    windows = (window, window) if window else None
    count = num_blocks if enabled else 0
    blocks = [
        WindowBlock(AttentionLayer(channels, ffn_ratio), AttentionLayer(channels, ffn_ratio), size, windows)
        for _ in range(count)
    ]
    return FeatureEnhancement(blocks)
