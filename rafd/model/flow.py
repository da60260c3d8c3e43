"""Flow estimation (paper 2.2): shared conv encoder, pose alignment, global cross-attention, cost volume.

Output flow [B, 2, Hf, Wf] in metres on the CURRENT frame's grid: where each cell's content is now
minus where it was in the previous frame (ego motion removed by the alignment), channel 0 = x right,
channel 1 = y forward.

Speed option (flow.stride > output_stride, not the paper's): the features are average-pooled by
`pool` before phi, the whole matching runs on the coarse grid, and the flow (metres, so no rescaling)
is upsampled bilinearly to the detection grid.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from rafd.model.align import align_to_current
from rafd.model.attention import AttentionLayer


def global_correlation(current: Tensor, previous: Tensor) -> Tensor:
    """Cost volume C = E_cur E_prev^T / sqrt(C): [B, N, C] x [B, N, C] -> [B, N, N] (rows: current cells).

    Always float32, also under bf16/fp16 autocast: the softmax over N cells turns logit errors of a reduced
    precision (~0.4% for bf16) into match-probability errors, i.e. flow errors of a good fraction of a cell."""
    with torch.autocast(current.device.type, enabled=False):
        current, previous = current.float(), previous.float()
        return (current / math.sqrt(current.shape[-1])) @ previous.transpose(1, 2)  # [B, N, N] (scale the cheap side)


def flow_from_correlation(correlation: Tensor, grid: Tensor) -> Tensor:
    """GMFlow's global_correlation_softmax: V = G - softmax(C) G. [B, N, N], grid [N, 2] -> [B, N, 2] (float32)."""
    with torch.autocast(correlation.device.type, enabled=False):
        probability = correlation.float().softmax(dim=-1)  # [B, N, N], a match distribution over previous cells
        grid = grid.float()
        matched = probability @ grid  # [B, N, 2] expected previous position (aligned grid = current coords)
        return grid[None] - matched  # [B, N, 2]


def build_flow_encoder(channels: int) -> nn.Sequential:
    """phi: [B, C, Hf, Wf] -> [B, C/2, Hf, Wf], two conv3x3 + BN (ReLU between), shared by all frames."""
    half = channels // 2
    return nn.Sequential(
        nn.Conv2d(channels, half, 3, padding=1, bias=False),
        nn.BatchNorm2d(half),
        nn.ReLU(inplace=True),
        nn.Conv2d(half, half, 3, padding=1, bias=False),
        nn.BatchNorm2d(half),
    )


class FlowEstimator(nn.Module):
    """(S_prev, S_cur [B, C, Hf, Wf], relative_pose [B, 3]) -> flow [B, 2, Hf, Wf] metres.

    Matching runs on a grid of Hm = Hf / pool cells (pool = flow.stride / output_stride, 1 in the paper);
    `position` and `centres` belong to that grid.
    """

    # buffers (register_buffer in __init__), declared so that type checkers know them as tensors
    position: Tensor
    centres: Tensor

    def __init__(
        self,
        encoder: nn.Module,
        cross_layers: list[AttentionLayer],
        position: Tensor,
        centres: Tensor,
        half_extent: float,
        pool: int = 1,
    ) -> None:
        super().__init__()
        self.encoder = encoder
        self.cross_layers = nn.ModuleList(cross_layers)
        self.half_extent = half_extent
        self.pool = pool
        # Static per config, rebuilt by build_model: kept out of the state dict.
        self.register_buffer("position", position, persistent=False)  # [Hm*Wm, C/2]
        self.register_buffer("centres", centres, persistent=False)  # [Hm*Wm, 2] metres

    def encode(self, features: Tensor) -> Tensor:
        """phi on the matching grid: [B, C, Hf, Wf] -> [B, C/2, Hm, Wm]."""
        if self.pool > 1:
            # a coarse cell is the mean of its pool x pool fine cells, centred where its centre is
            features = F.avg_pool2d(features, self.pool)  # [B, C, Hm, Wm]
        return self.encoder(features)

    def match(self, e_prev: Tensor, e_cur: Tensor, relative_pose: Tensor) -> Tensor:
        """E_prev, E_cur [B, C/2, Hm, Wm], relative_pose [B, 3] -> flow [B, 2, Hf, Wf] metres."""
        batch, _, height, width = e_cur.shape
        e_prev = align_to_current(e_prev, e_cur, relative_pose, self.centres, self.half_extent)  # current grid
        e_prev = e_prev.flatten(2).transpose(1, 2) + self.position  # [B, Hm*Wm, C/2]
        e_cur = e_cur.flatten(2).transpose(1, 2) + self.position  # [B, Hm*Wm, C/2]
        for layer in self.cross_layers:
            # paper eq. (2): previous attends current, then current attends the updated previous (shared T_c)
            e_prev = layer(e_prev, e_cur)
            e_cur = layer(e_cur, e_prev)
        flow = flow_from_correlation(global_correlation(e_cur, e_prev), self.centres)  # [B, Hm*Wm, 2]
        flow = flow.transpose(1, 2).reshape(batch, 2, height, width)  # [B, 2, Hm, Wm]
        if self.pool > 1:
            # metres are metres on any grid: only resample (half-pixel centres match the cell geometry)
            flow = F.interpolate(
                flow, size=(height * self.pool, width * self.pool), mode="bilinear", align_corners=False
            )  # [B, 2, Hf, Wf]
        return flow

    def forward(self, previous: Tensor, current: Tensor, relative_pose: Tensor) -> Tensor:
        batch = current.shape[0]
        # phi on both frames in one call: same weights and (in training) the same BN batch statistics.
        encoded = self.encode(torch.cat([previous, current], dim=0))  # [2B, C/2, Hm, Wm]
        return self.match(encoded[:batch], encoded[batch:], relative_pose)
