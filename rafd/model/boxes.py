"""Box decoding: per-query regression at a cell -> (x, y, width, length, yaw) in the ego frame."""
from __future__ import annotations

import torch
from torch import Tensor

# exp() guard: e^6 = 403 m is far beyond any vehicle, and keeps an untrained model's boxes finite.
MAX_LOG_SIZE = 6.0


def decode_boxes(centres: Tensor, offset: Tensor, log_size: Tensor, rotation: Tensor, cell_size: float) -> Tensor:
    """centres [B, K, 2] m, offset [B, K, 2] cells, log_size [B, K, 2], rotation [B, K, 2] (sin, cos) -> [B, K, 5]."""
    xy = centres + offset * cell_size  # [B, K, 2] metres (x right, y forward like the offsets)
    size = torch.exp(log_size.clamp(-MAX_LOG_SIZE, MAX_LOG_SIZE))  # [B, K, 2] (width, length) metres
    yaw = torch.atan2(rotation[..., 0], rotation[..., 1])[..., None]  # [B, K, 1]
    return torch.cat([xy, size, yaw], dim=-1)  # [B, K, 5]
