"""Where the BEV flow is measured: a per-cell validity in [0, 1] from geometry alone (torch-free).

The flow of a cell is found by comparing it with the previous frame around the same place (after ego motion). Two
things bound what it can see, both known without the network:
- the previous frame's crop: content that was outside it has nothing to be compared with (the model then reads
  its own frame there, so the flow is ~0 by construction, not measured);
- the search window: cut symmetrically at the crop's edge (rafd.model.flow.symmetric_window_mask), a cell k
  matching cells from the edge measures motions of up to k cells only, and the outermost ring none.
validity = min(reach in the current crop, reach of the cell's previous position in the previous crop) / the full
search reach, clipped to [0, 1]: 1 = the flow was measured over the network's whole search range, 0 = not at all.
The same function serves the answer (service), the pictures and `rafd eval`'s flow tables.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np

from rafd import geometry

FLOW_VALID_MIN = 1.0  # pictures draw, and the answer's boolean form keeps, the cells measured over the full range


def search_reach_m(flow_stride: int, resolution: float, local_radius: int) -> float:
    """-> metres the flow's search reaches from a cell: local_radius matching cells (0 = global matching: one)."""
    return max(local_radius, 1) * flow_stride * resolution


def config_validity(cfg: Any, relative_pose: np.ndarray | None = None) -> np.ndarray:
    """A RaFDConfig's flow validity [Hf, Wf] for the pair's relative pose (previous -> current ego,
    geometry.relative_pose(pose_prev, pose_cur)); None: identity (no motion known)."""
    pose = np.zeros(3) if relative_pose is None else np.asarray(relative_pose, np.float64)
    reach = search_reach_m(cfg.flow.stride, cfg.resolution, cfg.flow.local_radius)
    return flow_validity(pose, cfg.feature_size, cfg.input_size, cfg.resolution, cfg.flow.stride, reach)


def flow_validity(
    relative_pose: np.ndarray,
    feature_size: int,
    input_size: int,
    resolution: float,
    flow_stride: int,
    reach_m: float,
) -> np.ndarray:
    """relative_pose [3] (previous -> current ego, geometry.relative_pose(pose_prev, pose_cur)) -> [Hf, Wf] float32.

    Distances are to the edge of the span of matching-cell centres (a square crop: the Chebyshev distance)."""
    half = 0.5 * input_size * resolution
    edge = half - 0.5 * flow_stride * resolution  # the outermost matching cell's centre: reach 0
    x, y, distance_now = _cell_centres(feature_size, input_size, resolution)  # [Hf, Wf] each, current frame
    # The centres' previous positions: transform_points(invert_pose(relative_pose), centres) = R(yaw)^T (c - t),
    # written out on the two coordinate planes (the service answers it per frame: 0.03 ms instead of 0.6 for 64 x 64,
    # the same float32 values).
    tx, ty, yaw = (float(v) for v in np.asarray(relative_pose, np.float64).reshape(3))
    cos, sin = math.cos(yaw), math.sin(yaw)
    u, v = x - tx, y - ty
    previous_x = u * cos
    previous_x += v * sin
    previous_y = v * cos
    previous_y -= u * sin
    # min(edge - now, edge - before) = edge - max(now, before): the Chebyshev distances of both positions
    distance = np.maximum(np.abs(previous_x, out=previous_x), np.abs(previous_y, out=previous_y), out=previous_x)
    np.maximum(distance, distance_now, out=distance)
    reach = np.subtract(edge, distance, out=distance)  # [Hf, Wf] metres of search reach left
    reach /= reach_m
    return np.clip(reach, 0.0, 1.0, out=reach).astype(np.float32)


@functools.lru_cache(maxsize=16)
def _cell_centres(feature_size: int, input_size: int, resolution: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x, y, Chebyshev distance from the radar) [Hf, Wf] each of the feature cells' centres, read-only."""
    centres = geometry.feature_cell_centres(feature_size, input_size, resolution)  # [Hf, Wf, 2]
    x, y = np.ascontiguousarray(centres[..., 0]), np.ascontiguousarray(centres[..., 1])
    distance = np.maximum(np.abs(x), np.abs(y))
    for array in (x, y, distance):
        array.flags.writeable = False
    return x, y, distance
