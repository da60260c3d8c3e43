"""FPN-style top-down neck: all backbone stages fused into ONE BEV map at the finest stage's stride."""

from __future__ import annotations

from torch import Tensor, nn
from torch.nn import functional as F


class FPNNeck(nn.Module):
    """list of [B, C_k, S/(4*2^k), S/(4*2^k)] -> [B, C, S/4, S/4]."""

    def __init__(self, in_channels: tuple[int, ...], channels: int) -> None:
        super().__init__()
        self.lateral = nn.ModuleList(nn.Conv2d(c, channels, 1) for c in in_channels)
        # A 3x3 conv after the sum smooths the nearest-neighbour upsampling seams (FPN's output conv).
        self.output = nn.Sequential(
            nn.Conv2d(channels, channels, 3, padding=1, bias=False), nn.BatchNorm2d(channels), nn.ReLU(inplace=True)
        )

    def forward(self, stages: list[Tensor]) -> Tensor:
        fused = self.lateral[-1](stages[-1])  # coarsest level
        for level in range(len(stages) - 2, -1, -1):
            lateral = self.lateral[level](stages[level])
            # upsample to the finer stage's (static) size: also right when a stride-2 conv rounded up
            fused = lateral + F.interpolate(fused, size=lateral.shape[-2:], mode="nearest")
        return self.output(fused)  # [B, C, S/4, S/4]
