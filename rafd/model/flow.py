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


LOCAL_MASKED = -1.0e4  # additive logit of a masked offset: exp(-1e4) == 0 in float32


def shift_kernels(channels: int, radius: int) -> Tensor:
    """One-hot 3x3.. kernels that copy every channel at every offset: [C * D, 1, k, k], D = k^2, k = 2r + 1.

    A grouped convolution (groups = C) with them turns [B, C, H, W] into [B, C * D, H, W] whose channel c * D + d is
    channel c read at offset d = (di, dj) row-major from (-r, -r): out[i, j] = x[i + di, j + dj], zeros outside."""
    size = 2 * radius + 1
    offsets = size * size
    kernels = torch.zeros(offsets, 1, size, size)
    kernels.view(offsets, size * size)[torch.arange(offsets), torch.arange(offsets)] = 1.0
    return kernels.repeat(channels, 1, 1, 1)  # [C * D, 1, k, k]


def local_offsets(radius: int, cell: float) -> Tensor:
    """-> [D, 2] metres (x right, y forward) from a cell to the previous cell it is compared with at offset d."""
    steps = torch.arange(-radius, radius + 1, dtype=torch.float32)
    di, dj = torch.meshgrid(steps, steps, indexing="ij")  # rows down, columns right
    return torch.stack([dj.flatten() * cell, -di.flatten() * cell], dim=-1)  # [D, 2]


def symmetric_window_mask(size: int, radius: int) -> Tensor:
    """-> [1, D, H, W] additive logits: LOCAL_MASKED where offset d = (di, dj) reaches further than the cell's
    distance to the map's edge along that axis (|di| > min(i, H-1-i) or |dj| > min(j, W-1-j)).

    Why symmetric and not just "inside the map": a cell whose match is ambiguous (speckle, empty road) spreads its
    softmax over its window, and a window cut on one side only has a mean offset pointing inwards: a flow of up to
    r/2 cells around the border that no motion caused. Cut to the same reach on both sides, a flat match averages
    to zero; the edge cells can only report motion up to their distance from the edge (0 on the outermost ring)."""
    steps = torch.arange(-radius, radius + 1)
    di, dj = torch.meshgrid(steps, steps, indexing="ij")
    index = torch.arange(size)
    reach = torch.minimum(index, size - 1 - index)  # [H] cells to the nearer edge
    rows_ok = di.flatten()[:, None, None].abs() <= reach[None, :, None]  # [D, H, 1]
    cols_ok = dj.flatten()[:, None, None].abs() <= reach[None, None, :]  # [D, 1, W]
    return torch.where(rows_ok & cols_ok, 0.0, LOCAL_MASKED)[None]


def local_correlation(current: Tensor, previous: Tensor, kernels: Tensor) -> Tensor:
    """Local cost volume: E_cur, E_prev [B, C, H, W] -> [B, D, H, W], E_cur . E_prev(offset d) / sqrt(C)."""
    batch, channels, height, width = previous.shape
    with torch.autocast(current.device.type, enabled=False):  # float32, as the global cost volume
        radius = kernels.shape[-1] // 2
        shifted = F.conv2d(previous.float(), kernels, padding=radius, groups=channels)  # [B, C*D, H, W]
        shifted = shifted.reshape(batch, channels, -1, height, width)  # [B, C, D, H, W]
        scaled = current.float() * (1.0 / math.sqrt(channels))  # [B, C, H, W]
        return (shifted * scaled[:, :, None]).sum(dim=1)  # [B, D, H, W]


def flow_from_local_correlation(correlation: Tensor, offsets: Tensor, mask: Tensor) -> Tensor:
    """[B, D, H, W] costs, offsets [D, 2] m, mask [1, D, H, W] -> flow [B, 2, H, W] m: V = -sum_d softmax_d(C) o_d
    (the content now at the cell was at the cell + the expected offset)."""
    with torch.autocast(correlation.device.type, enabled=False):
        probability = (correlation.float() + mask).softmax(dim=1)  # [B, D, H, W]
        # the expectation over D as one 1x1 convolution with the (negated) offsets as weights
        return F.conv2d(probability, -offsets.t()[:, :, None, None])  # [B, 2, H, W]


def build_flow_encoder(channels: int, out_channels: int | None = None) -> nn.Sequential:
    """phi: [B, C, Hf, Wf] -> [B, Ce, Hf, Wf] (Ce = out_channels, default C/2), two conv3x3 + BN (ReLU between),
    shared by all frames."""
    half = out_channels or channels // 2
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
    kernels: Tensor
    offsets: Tensor
    mask: Tensor

    def __init__(
        self,
        encoder: nn.Module,
        cross_layers: list[AttentionLayer],
        position: Tensor,
        centres: Tensor,
        half_extent: float,
        pool: int = 1,
        local_radius: int = 0,
    ) -> None:
        super().__init__()
        self.encoder = encoder
        self.cross_layers = nn.ModuleList(cross_layers)
        self.half_extent = half_extent
        self.pool = pool
        self.local_radius = local_radius  # 0: global matching (the paper)
        # Static per config, rebuilt by build_model: kept out of the state dict.
        self.register_buffer("position", position, persistent=False)  # [Hm*Wm, C/2]
        self.register_buffer("centres", centres, persistent=False)  # [Hm*Wm, 2] metres
        size = math.isqrt(centres.shape[0])
        channels = position.shape[1]
        if local_radius:
            cell = 2.0 * half_extent / size
            self.register_buffer("kernels", shift_kernels(channels, local_radius), persistent=False)
            self.register_buffer("offsets", local_offsets(local_radius, cell), persistent=False)  # [D, 2] m
            self.register_buffer("mask", symmetric_window_mask(size, local_radius), persistent=False)  # [1, D, Hm, Wm]

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
        if self.local_radius and len(self.cross_layers) == 0:
            # the CPU recipe: the local cost volume on the maps themselves, no token layout at all
            correlation = local_correlation(e_cur, e_prev, self.kernels)  # [B, D, Hm, Wm]
            flow = flow_from_local_correlation(correlation, self.offsets, self.mask)  # [B, 2, Hm, Wm]
        else:
            e_prev_tokens = e_prev.flatten(2).transpose(1, 2) + self.position  # [B, Hm*Wm, C/2]
            e_cur_tokens = e_cur.flatten(2).transpose(1, 2) + self.position  # [B, Hm*Wm, C/2]
            for layer in self.cross_layers:
                # paper eq. (2): previous attends current, then current attends the updated previous (shared T_c)
                e_prev_tokens = layer(e_prev_tokens, e_cur_tokens)
                e_cur_tokens = layer(e_cur_tokens, e_prev_tokens)
            if self.local_radius:
                as_map = (batch, -1, height, width)
                correlation = local_correlation(
                    e_cur_tokens.transpose(1, 2).reshape(as_map),
                    e_prev_tokens.transpose(1, 2).reshape(as_map),
                    self.kernels,
                )  # [B, D, Hm, Wm]
                flow = flow_from_local_correlation(correlation, self.offsets, self.mask)  # [B, 2, Hm, Wm]
            else:
                flow = flow_from_correlation(global_correlation(e_cur_tokens, e_prev_tokens), self.centres)
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
