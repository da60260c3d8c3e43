"""Fixed 2D sine position encoding (DETR / GMFlow PositionEmbeddingSine, normalised coordinates)."""

from __future__ import annotations

import math

import torch
from torch import Tensor


def sine_position_encoding(channels: int, height: int, width: int, temperature: float = 10000.0) -> Tensor:
    """-> [H*W, channels]: first half encodes the row, second half the column, sin/cos interleaved."""
    y = (torch.arange(height, dtype=torch.float32) + 0.5) / height * 2 * math.pi  # [H]
    x = (torch.arange(width, dtype=torch.float32) + 0.5) / width * 2 * math.pi  # [W]
    y, x = torch.meshgrid(y, x, indexing="ij")  # [H, W] each
    parts = []
    for coord, count in ((y, channels // 2), (x, channels - channels // 2)):
        index = torch.arange(count, dtype=torch.float32)
        freq = temperature ** (2 * torch.div(index, 2, rounding_mode="floor") / max(count, 1))  # [count]
        phase = coord[..., None] / freq  # [H, W, count]
        # even channels sin, odd channels cos (same frequency per pair)
        parts.append(torch.where(index.long() % 2 == 0, phase.sin(), phase.cos()))
    return torch.cat(parts, dim=-1).reshape(height * width, channels)  # [H*W, C]
