"""Joint flow-guided propagation (the CPU recipe's, not the paper's): every past frame read in one sampling.

The paper chains T-1 propagations (T_t = blocks(S_t, T_{t-1}), oldest -> newest), so a new frame re-runs the whole
chain: (T-1) x blocks deformable layers and T-1 feature alignments per streaming step. Here the newest frame's cells
are the queries and the past frames' own features S_{t-a} (a = 1 .. T-1, what a stream caches anyway) the values,
all read by ONE deformable attention whose points and softmax weights span frames x points (Deformable DETR's
multi-level sampling, with frames as the levels):

    reference_a = E_a(r_t - a V_t)     (r_t the cell, V_t the newest pair's flow, E_a the ego motion into frame t-a)

i.e. the content is followed back at constant velocity (0.25 s frames: a vehicle's speed changes little over three
of them) and then through the ego motion into the past frame's own grid, so no past map is resampled first. The
vanilla ablation (flow_guided False) uses r_t moved by the ego motion only.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import cast

import torch
from torch import Tensor, nn

from rafd.model.align import metres_to_grid, relative_pose_torch
from rafd.model.deformable import DeformableAttention, DeformableLayer, deformable_sample_points_major, linear_on_map


def to_past_frames(points: Tensor, relative_pose: Tensor) -> Tensor:
    """Current-frame points [B, F, Q, 2] -> each past frame's points [B, F, Q, 2].

    relative_pose [B, F, 3] = relative_pose_torch(pose_past, pose_current) maps past-frame points into the current
    frame (p_cur = R p_past + t), so p_past = R^T (p_cur - t)."""
    cos = torch.cos(relative_pose[..., 2:3])  # [B, F, 1]
    sin = torch.sin(relative_pose[..., 2:3])
    dx = points[..., 0] - relative_pose[..., 0:1]  # [B, F, Q]
    dy = points[..., 1] - relative_pose[..., 1:2]
    return torch.stack([cos * dx + sin * dy, -sin * dx + cos * dy], dim=-1)  # [B, F, Q, 2]


class JointDeformableAttention(DeformableAttention):
    """query map [B, C, H, W], references [B, F, H*W, 2] (normalised, one per past frame), values [B, F, C, H, W]
    -> [B, C, H, W]: num_points samples in each of the F frames, one softmax over all F x num_points, values read in
    value_channels."""

    def __init__(
        self, channels: int, num_frames: int, num_points: int, map_size: tuple[int, int], value_channels: int
    ) -> None:
        super().__init__(channels, num_frames * num_points, map_size)
        self.frames = num_frames
        self.points_per_frame = num_points
        # Values are sampled in value_channels (< C): GridSample's cost is per sampled channel, and it is the
        # largest single operation of the step; the output projection brings them back to C.
        self.value_proj = nn.Conv2d(channels, value_channels, 1)
        self.output_proj = nn.Linear(value_channels, channels)
        nn.init.xavier_uniform_(self.value_proj.weight)
        nn.init.zeros_(cast(Tensor, self.value_proj.bias))
        nn.init.xavier_uniform_(self.output_proj.weight)
        nn.init.zeros_(self.output_proj.bias)

    def forward_map(self, query: Tensor, reference: Tensor, value: Tensor) -> Tensor:
        batch, channels, height, width = query.shape
        frames, points = self.frames, self.points_per_frame
        cells = height * width
        offsets = linear_on_map(self.sampling_offsets, query)  # [B, F*P*2, H, W] cells, channel = (f*P + p)*2 + xy
        offsets = offsets.reshape(batch, frames, points, 2, cells).transpose(3, 4)  # [B, F, P, Q, 2]
        locations = reference[:, :, None] + offsets * self.cell  # [B, F, P, Q, 2]
        weights = linear_on_map(self.attention_weights, query).flatten(2).softmax(dim=1)  # [B, F*P, Q]
        values = self.value_proj(value.reshape(batch * frames, channels, height, width))  # [B*F, Cv, H, W]
        sampled = deformable_sample_points_major(
            values, locations.reshape(batch * frames, points, cells, 2), weights.reshape(batch * frames, points, cells)
        ).reshape(batch, frames, -1, cells)  # [B, F, Cv, Q]
        out = sampled[:, 0]
        for frame in range(1, frames):  # adds, not ReduceSum (see deformable_sample_points_major)
            out = out + sampled[:, frame]
        return linear_on_map(self.output_proj, out.reshape(batch, -1, height, width))  # [B, C, H, W]


class JointPropagation(nn.Module):
    """The window's features [B, T, C, Hf, Wf], flows [B, T-1, 2, Hf, Wf], poses [B, T, 3] -> [B, C, Hf, Wf]."""

    centres: Tensor  # a buffer (register_buffer in __init__), declared so that type checkers know it as a tensor
    ages: Tensor

    def __init__(
        self, layers: list[DeformableLayer], centres: Tensor, half_extent: float, flow_guided: bool, num_frames: int
    ) -> None:
        super().__init__()
        self.layers = nn.ModuleList(layers)
        self.half_extent = half_extent
        self.flow_guided = flow_guided
        self.register_buffer("centres", centres, persistent=False)  # [Hf*Wf, 2] metres
        # frames before the newest, oldest first: ages T-1 .. 1 (in frames)
        self.register_buffer("ages", torch.arange(num_frames - 1, 0, -1, dtype=torch.float32), persistent=False)

    def reference_points(self, flow: Tensor, relative: Tensor) -> Tensor:
        """newest flow [B, 2, Hf, Wf] m, relative poses past -> current [B, F, 3] -> [B, F, Hf*Wf, 2] normalised."""
        here = self.centres[None, None].to(flow.dtype)  # [1, 1, Q, 2] metres, r_t
        if self.flow_guided:
            velocity = flow.flatten(2).transpose(1, 2)[:, None]  # [B, 1, Q, 2] metres per frame
            here = here - self.ages.to(flow.dtype)[None, :, None, None] * velocity  # [B, F, Q, 2]
        else:
            here = here.expand(flow.shape[0], relative.shape[1], -1, -1)  # [B, F, Q, 2]
        return metres_to_grid(to_past_frames(here, relative), self.half_extent)  # [B, F, Q, 2]

    def propagate(self, features: Tensor, flows: Tensor, poses: Tensor) -> Tensor:
        return self(features[:, :-1], features[:, -1], flows, poses)

    def forward(self, past: Tensor, current: Tensor, flows: Tensor, poses: Tensor) -> Tensor:
        """past [B, F, C, Hf, Wf] (F = T-1, oldest first), current [B, C, Hf, Wf], flows [B, F, 2, Hf, Wf],
        poses [B, T, 3] -> [B, C, Hf, Wf]. The module's call (not a plain method), so that the ONNX exporter names
        its nodes /propagation/... (a method's nodes get its caller's scope)."""
        newest = poses[:, -1:].expand(-1, past.shape[1], -1)  # [B, F, 3]
        relative = relative_pose_torch(poses[:, :-1], newest).to(current.dtype)  # [B, F, 3] past -> current
        reference = self.reference_points(flows[:, -1], relative)  # [B, F, Q, 2]
        x = current  # queries: the newest frame's cells
        for layer in cast("Iterable[DeformableLayer]", self.layers):
            x = layer(x, reference, past)  # forward_map: [B, C, Hf, Wf]
        return x
