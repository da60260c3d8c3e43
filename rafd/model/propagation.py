"""Flow-guided propagation (paper 2.3): deformable attention from the current cells into the previous map.

Queries are the current frame's cells; values the previous propagated map T_{t-1} aligned to the
current grid by the ego pose; each query's reference point is its own cell moved back by the
estimated flow, r_t - V (where its content was), or r_t itself for the vanilla ablation.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import cast

from torch import Tensor, nn

from rafd.model.align import align_to_current, metres_to_grid, relative_pose_torch
from rafd.model.deformable import DeformableLayer


class FlowGuidedPropagation(nn.Module):
    """(S_t, T_{t-1} [B, C, Hf, Wf], flow [B, 2, Hf, Wf] m, relative_pose [B, 3]) -> T_t [B, C, Hf, Wf]."""

    centres: Tensor  # a buffer (register_buffer in __init__), declared so that type checkers know it as a tensor

    def __init__(self, layers: list[DeformableLayer], centres: Tensor, half_extent: float, flow_guided: bool) -> None:
        super().__init__()
        self.layers = nn.ModuleList(layers)
        self.half_extent = half_extent
        self.flow_guided = flow_guided
        self.register_buffer("centres", centres, persistent=False)  # [Hf*Wf, 2] metres

    def reference_points(self, flow: Tensor) -> Tensor:
        """flow [B, 2, Hf, Wf] metres -> [B, Hf*Wf, 2] normalised sampling centres r_t - V."""
        here = self.centres[None].to(flow.dtype)  # [1, Hf*Wf, 2] metres, r_t
        if self.flow_guided:
            here = here - flow.flatten(2).transpose(1, 2)  # [B, Hf*Wf, 2] metres, where the content was
        else:
            here = here.expand(flow.shape[0], -1, -1)  # [B, Hf*Wf, 2]
        # metres_to_grid flips y: flow forward (+y) is image up, i.e. towards smaller rows
        return metres_to_grid(here, self.half_extent)

    def propagate(self, features: Tensor, flows: Tensor, poses: Tensor) -> Tensor:
        """The window: features [B, T, C, Hf, Wf], flows [B, T-1, 2, Hf, Wf], poses [B, T, 3] -> T_T [B, C, Hf, Wf],
        chained oldest -> newest with one shared module for every pair."""
        # relative poses in the poses' own dtype (float64 world coordinates keep cm precision)
        relative = relative_pose_torch(poses[:, :-1], poses[:, 1:]).to(features.dtype)  # [B, T-1, 3]
        propagated = features[:, 0]  # T_1 = S_1
        for t in range(1, features.shape[1]):
            propagated = self(features[:, t], propagated, flows[:, t - 1], relative[:, t - 1])
        return propagated

    def forward(self, current: Tensor, previous: Tensor, flow: Tensor, relative_pose: Tensor) -> Tensor:
        aligned = align_to_current(previous, current, relative_pose, self.centres, self.half_extent)  # [B, C, Hf, Wf]
        reference = self.reference_points(flow)  # [B, Hf*Wf, 2]
        # every cell is a query: the layers work on the channel-major map itself (no [B, Hf*Wf, C] transposes)
        x = current
        for layer in cast("Iterable[DeformableLayer]", self.layers):  # the ModuleList of __init__'s layers
            x = layer(x, reference, aligned)  # forward_map: [B, C, Hf, Wf]
        return x
