"""Box decoding: per-query regression at a cell -> (x, y, width, length, yaw) in the ego frame."""

from __future__ import annotations

import math

import torch
from torch import Tensor

# exp() guard: e^6 = 403 m is far beyond any vehicle, and keeps an untrained model's boxes finite.
MAX_LOG_SIZE = 6.0


def decode_boxes(
    centres: Tensor, offset: Tensor, log_size: Tensor, rotation: Tensor, cell_size: float, encoding: str = "symmetric"
) -> Tensor:
    """centres [B, K, 2] m, offset [B, K, 2] cells, log_size [B, K, 2], rotation [B, K, 2] -> [B, K, 5].

    encoding "symmetric" (rafd.config.HeadConfig.box_encoding): rotation is (sin 2yaw, cos 2yaw); the box comes out
    canonical like the targets (rafd.data.targets.canonical_boxes): width <= length, yaw in [-pi/2, pi/2).
    "as_labelled": rotation is (sin yaw, cos yaw), sizes as regressed.
    """
    xy = centres + offset * cell_size  # [B, K, 2] metres (x right, y forward like the offsets)
    size = torch.exp(log_size.clamp(-MAX_LOG_SIZE, MAX_LOG_SIZE))  # [B, K, 2] (width, length) metres
    angle = torch.atan2(rotation[..., 0], rotation[..., 1])[..., None]  # [B, K, 1]
    if encoding == "as_labelled":
        return torch.cat([xy, size, angle], dim=-1)  # [B, K, 5]
    width, length = size[..., :1], size[..., 1:]  # [B, K, 1] each
    swap = width > length  # the same rectangle turned by 90 degrees with the sides exchanged
    yaw = torch.where(swap, angle / 2.0 + math.pi / 2.0, angle / 2.0)  # [B, K, 1]
    yaw = yaw - math.pi * torch.floor(yaw / math.pi + 0.5)  # modulo pi, in [-pi/2, pi/2)
    return torch.cat([xy, torch.minimum(width, length), torch.maximum(width, length), yaw], dim=-1)  # [B, K, 5]
