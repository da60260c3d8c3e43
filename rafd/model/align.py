"""SE(2) ego-motion compensation of BEV feature maps (torch twins of rafd.geometry's pose maths).

Every map in the model is a grid of Hf x Wf cells centred on the radar; cell (i, j) has its centre
at x = (j + 0.5 - Wf/2) * cell, y = (Hf/2 - i - 0.5) * cell metres (geometry.feature_cell_centres).
grid_sample (align_corners=False) addresses the same map with normalised coordinates in [-1, 1]:
column axis = x / half_extent, row axis = -y / half_extent (image rows grow backwards in y),
half_extent = Wf * cell / 2 metres.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor
from torch.nn import functional as F

from rafd import geometry


def cell_centres(feature_size: int, input_size: int, resolution: float) -> Tensor:
    """-> [Hf*Wf, 2] metres of every cell centre, flat index i * Wf + j (numpy geometry is the truth)."""
    centres = geometry.feature_cell_centres(feature_size, input_size, resolution)  # [Hf, Wf, 2]
    return torch.from_numpy(centres.reshape(-1, 2).astype(np.float32))  # [Hf*Wf, 2]


def metres_to_grid(xy: Tensor, half_extent: float) -> Tensor:
    """[..., 2] metres (x right, y forward) -> [..., 2] grid_sample coordinates (x, y down) in [-1, 1]."""
    return torch.stack([xy[..., 0] / half_extent, -xy[..., 1] / half_extent], dim=-1)


def relative_pose_torch(pose_from: Tensor, pose_to: Tensor) -> Tensor:
    """[..., 3] world poses -> [..., 3], torch twin of geometry.relative_pose(pose_from, pose_to).

    The result maps points of the `pose_from` ego frame into the `pose_to` ego frame:
    p_to = R(yaw) p_from + (x, y).  (inverse(to) o from, yaw wrapped to (-pi, pi].)
    """
    dx = pose_from[..., 0] - pose_to[..., 0]
    dy = pose_from[..., 1] - pose_to[..., 1]
    cos_to, sin_to = torch.cos(pose_to[..., 2]), torch.sin(pose_to[..., 2])
    # R(-yaw_to) @ (t_from - t_to): the `from` origin seen from the `to` ego.
    x = cos_to * dx + sin_to * dy
    y = -sin_to * dx + cos_to * dy
    dyaw = pose_from[..., 2] - pose_to[..., 2]
    yaw = torch.atan2(torch.sin(dyaw), torch.cos(dyaw))
    return torch.stack([x, y, yaw], dim=-1)


def current_to_previous(points: Tensor, relative_pose: Tensor) -> Tensor:
    """Current-frame points [N, 2] -> previous-frame points [B, N, 2].

    relative_pose [B, 3] = relative_pose_torch(pose_prev, pose_cur) maps previous-frame points into the
    current frame (p_cur = R p_prev + t), so the inverse is p_prev = R^T (p_cur - t).
    """
    cos = torch.cos(relative_pose[:, 2])[:, None]  # [B, 1]
    sin = torch.sin(relative_pose[:, 2])[:, None]  # [B, 1]
    dx = points[None, :, 0] - relative_pose[:, 0:1]  # [B, N]
    dy = points[None, :, 1] - relative_pose[:, 1:2]  # [B, N]
    return torch.stack([cos * dx + sin * dy, -sin * dx + cos * dy], dim=-1)  # [B, N, 2]


def align_to_current(
    previous: Tensor, current: Tensor, relative_pose: Tensor, centres: Tensor, half_extent: float
) -> Tensor:
    """Resample the previous frame's map on the current frame's grid: [B, C, Hf, Wf] -> [B, C, Hf, Wf].

    Each current cell centre is moved through the ego motion into the previous frame and read there
    bilinearly. Cells whose point leaves the span of the previous map's cell centres keep `current`
    (paper: out-of-range locations default to E_t): inside that span bilinear weights never touch the
    zero padding, so an aligned value is always a true interpolation, never faded towards zero.
    """
    batch, channels, height, width = previous.shape
    points = current_to_previous(centres.to(previous.dtype), relative_pose.to(previous.dtype))  # [B, Hf*Wf, 2]
    grid = metres_to_grid(points, half_extent)  # [B, Hf*Wf, 2]
    # Outermost cell centres sit at +-(1 - 1/W); a small tolerance keeps exact hits (identity pose,
    # whole-cell shifts) in range on every backend, and the clamp keeps those samples off the padding.
    limit = torch.tensor([1.0 - 1.0 / width, 1.0 - 1.0 / height], dtype=grid.dtype, device=grid.device)
    within = grid.abs() <= limit + 1e-4  # [B, Hf*Wf, 2]
    inside = within[..., 0] & within[..., 1]  # [B, Hf*Wf]
    grid = torch.maximum(torch.minimum(grid, limit), -limit)
    sampled = F.grid_sample(
        previous, grid.reshape(batch, height, width, 2), mode="bilinear", padding_mode="zeros", align_corners=False
    )  # [B, C, Hf, Wf]
    inside = inside.reshape(batch, 1, height, width)  # [B, 1, Hf, Wf]
    return torch.where(inside, sampled, current)
