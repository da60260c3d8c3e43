"""Velocity from the model's BEV flow: a box's flow sampled on a generic grid, divided by the pair's interval.

The model's answer carries the newest pair's flow [2, Hf, Wf] in metres: where each cell's content is now minus
where it was one scan before, ego motion removed, in the newest scan's ego axes (x right, y forward), with a validity
[Hf, Wf] in [0, 1] (rafd.flow_validity: 1 = measured over the search's whole reach). A FlowGrid says where the cells
are in ego metres, so the same sampling serves the model's 256 px crop, one tile of a whole scan (the crop's grid
shifted by the tile's offset) and a mosaic of tiles (a sequence of FlowFields: each box reads the field that
measured it best).

What the flow cannot see: a motion of more than the search reach per scan (rafd.flow_validity.search_reach_m:
4.2 m, 16.7 m/s at 4 Hz for the shipped model). The matching then finds the best cell inside its window, at or
near the window's edge, so the flow says "about the reach" whatever the true motion: a box whose flow reaches
`reach_fraction` of its reach (scaled by the cells' validity, the reach left near the crop's edge) is SATURATED and
gives no measurement; the track's filter carries its velocity (velocity_source "track"), or none for a new track.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class FlowGrid:
    """Cell (i, j) = (row, column) has its centre at ego metres x = origin_x + j * cell, y = origin_y - i * cell
    (rows run backwards, columns right: the scan's image layout)."""

    cell_size_m: float
    origin_m: tuple[float, float]  # ego metres (x, y) of cell (0, 0)'s centre
    shape: tuple[int, int]  # (Hf, Wf)

    @classmethod
    def centred(
        cls, height: int, width: int, cell_size_m: float, offset_m: tuple[float, float] = (0.0, 0.0)
    ) -> FlowGrid:
        """The grid of a crop centred `offset_m` (ego metres) from the radar: the service's CELL_RULE
        (x = (j + 0.5 - width/2) * cell, y = (height/2 - i - 0.5) * cell) shifted by the offset."""
        origin = (
            (0.5 - width / 2.0) * cell_size_m + float(offset_m[0]),
            (height / 2.0 - 0.5) * cell_size_m + float(offset_m[1]),
        )
        return cls(float(cell_size_m), origin, (int(height), int(width)))

    def cells_of(self, xy: np.ndarray) -> np.ndarray:
        """[N, 2] ego metres -> [N, 2] continuous (row, column) of the cell grid (cell centres at integers)."""
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        return np.stack([(self.origin_m[1] - xy[:, 1]), (xy[:, 0] - self.origin_m[0])], -1) / self.cell_size_m

    def centres(self) -> np.ndarray:
        """-> [Hf, Wf, 2] ego metres of every cell's centre."""
        rows, columns = np.meshgrid(np.arange(self.shape[0]), np.arange(self.shape[1]), indexing="ij")
        return np.stack([self.origin_m[0] + columns * self.cell_size_m, self.origin_m[1] - rows * self.cell_size_m], -1)


@dataclass(frozen=True)
class FlowField:
    """One pair's flow on one grid: flow [2, Hf, Wf] metres (x right, y forward, ego motion removed, the newest
    scan's ego axes), validity [Hf, Wf] in [0, 1] (None: 1 everywhere), the pair's interval in seconds (newest
    timestamp - previous), and the search reach in metres per pair (None: no saturation check)."""

    grid: FlowGrid
    flow: np.ndarray
    interval_s: float
    validity: np.ndarray | None = None
    reach_m: float | None = None

    def usable(self) -> bool:
        """Whether the field can measure anything: a positive finite interval and the grid's shape."""
        shape = tuple(self.grid.shape)
        flow_ok = np.shape(self.flow) == (2,) + shape
        validity_ok = self.validity is None or np.shape(self.validity) == shape
        return bool(flow_ok and validity_ok and math.isfinite(self.interval_s) and self.interval_s > 0)


@dataclass(frozen=True)
class FlowVelocity:
    """Per box: the velocity the flow measured (m/s, ego axes) and how much to trust it."""

    velocity: np.ndarray  # [N, 2] m/s; NaN where the flow measured nothing usable
    variance: np.ndarray  # [N] (m/s)^2 per axis (isotropic); NaN where velocity is
    validity: np.ndarray  # [N] mean validity of the cells behind it (centre: bilinear at the centre), 0 = none
    saturated: np.ndarray  # [N] bool: the flow reached its search limit (the motion may be larger)


def _prepared(field: FlowField) -> tuple[np.ndarray, np.ndarray]:
    """-> (flow [2, H*W], weight [H*W] in [0, 1]): a cell whose flow or validity is not finite weighs 0 and reads
    flow 0 (checked once per field; copies made only when something needs cleaning)."""
    flow = np.asarray(field.flow, np.float64).reshape(2, -1)
    weight = np.ones(flow.shape[1]) if field.validity is None else np.asarray(field.validity, np.float64).reshape(-1)
    finite = np.isfinite(flow).all(0) & np.isfinite(weight)
    if not finite.all():
        flow, weight = np.where(finite, flow, 0.0), np.where(finite, weight, 0.0)
    if weight.min(initial=0.0) < 0.0 or weight.max(initial=0.0) > 1.0:
        weight = np.clip(weight, 0.0, 1.0)
    return flow, weight


def _gather(
    field: FlowField, prepared: tuple[np.ndarray, np.ndarray], rows: np.ndarray, columns: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Integer cells [...] (off-grid ones too) -> (flow [2, ...] metres, weight [...], on the grid [...]): a cell
    off the grid weighs 0."""
    height, width = field.grid.shape
    inside = (rows >= 0) & (rows < height) & (columns >= 0) & (columns < width)
    flat = np.clip(rows, 0, height - 1) * width + np.clip(columns, 0, width - 1)
    flow, weight = prepared
    return flow[:, flat], np.where(inside, weight[flat], 0.0), inside


def sample_centre(
    field: FlowField, centres: np.ndarray, prepared: tuple[np.ndarray, np.ndarray] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Candidate (a): bilinear flow [N, 2] metres and validity [N] at box centres [N, 2]; cells off the grid or not
    finite count as validity 0 (so a centre off the grid reads validity 0)."""
    prepared = _prepared(field) if prepared is None else prepared
    cells = field.grid.cells_of(centres)  # [N, 2] (row, column)
    top = np.floor(cells)
    fraction = cells - top  # [N, 2]
    top = top.astype(np.int64)
    corner_rows = top[:, :1] + np.array([[0, 0, 1, 1]])  # [N, 4]
    corner_columns = top[:, 1:] + np.array([[0, 1, 0, 1]])
    row_share = np.where(np.array([0, 0, 1, 1]), fraction[:, :1], 1.0 - fraction[:, :1])  # [N, 4]
    column_share = np.where(np.array([0, 1, 0, 1]), fraction[:, 1:], 1.0 - fraction[:, 1:])
    flow, weight, _ = _gather(field, prepared, corner_rows, corner_columns)  # [2, N, 4], [N, 4]
    share = row_share * column_share * (weight > 0)  # off-grid corners add nothing
    return np.einsum("cnk,nk->nc", flow, share), (share * weight).sum(1)


def sample_box(
    field: FlowField,
    boxes: np.ndarray,
    max_half_cells: int = 12,
    prepared: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, ...]:
    """Candidate (b): over the cells whose centres lie in each box [N, 5] -> (validity-weighted mean flow [N, 2]
    metres, its weighted spread [N] metres per axis, the cells' mean validity [N], the number of cells [N]). A patch
    of at most 2 * max_half_cells + 1 cells per side around the centre is read (17 m of 0.69 m cells: a bus)."""
    flow, weight = _prepared(field) if prepared is None else prepared
    boxes = np.asarray(boxes, np.float64).reshape(-1, 5)
    height, width = field.grid.shape
    cell = field.grid.cell_size_m
    reach = np.hypot(boxes[:, 2], boxes[:, 3]).max(initial=0.0) / 2.0  # metres from a centre to a corner
    half = int(min(max_half_cells, math.ceil(reach / cell) + 1))
    steps = np.arange(-half, half + 1, dtype=np.float64)  # [P]
    cells = field.grid.cells_of(boxes[:, :2])  # [N, 2] continuous (row, column)
    centre = np.round(cells)
    # a patch cell (i, j) lies at (steps[j] - f_col, -(steps[i] - f_row)) cells from the box centre, f = cells -
    # centre; in the box's axes (R(-yaw)) both coordinates are a row term plus a column term: [N, P] each
    column_m = (steps[None, :] - (cells[:, 1:] - centre[:, 1:])) * cell  # [N, P] ego x offsets
    row_m = -(steps[None, :] - (cells[:, :1] - centre[:, :1])) * cell  # [N, P] ego y offsets
    cos, sin = np.cos(boxes[:, 4:5]), np.sin(boxes[:, 4:5])  # [N, 1]
    along_width = (cos * column_m)[:, None, :] + (sin * row_m)[:, :, None]  # [N, P, P]
    along_length = (-sin * column_m)[:, None, :] + (cos * row_m)[:, :, None]
    rows = centre[:, :1].astype(np.int64) + steps.astype(np.int64)[None, :]  # [N, P]
    columns = centre[:, 1:].astype(np.int64) + steps.astype(np.int64)[None, :]
    on_grid = ((rows >= 0) & (rows < height))[:, :, None] & ((columns >= 0) & (columns < width))[:, None, :]
    counted = (
        on_grid
        & (np.abs(along_width) <= boxes[:, 2, None, None] / 2.0)
        & (np.abs(along_length) <= boxes[:, 3, None, None] / 2.0)
    )  # [N, P, P]
    flat = (np.clip(rows, 0, height - 1) * width)[:, :, None] + np.clip(columns, 0, width - 1)[:, None, :]
    count = len(boxes)
    w = np.where(counted, weight[flat], 0.0).reshape(count, -1)  # [N, P*P]
    values = flow[:, flat].reshape(2, count, -1)  # [2, N, P*P]
    total = w.sum(1)  # [N]
    safe = np.where(total > 0, total, 1.0)
    mean = np.einsum("cnk,nk->nc", values, w) / safe[:, None]  # [N, 2]
    second = np.einsum("cnk,nk->n", values * values, w) / safe  # [N] sum over both axes of E[f^2]
    variance = np.maximum(second - (mean * mean).sum(1), 0.0) / 2.0  # per axis
    cells_in = counted.reshape(count, -1).sum(1)
    return mean, np.sqrt(variance), total / np.maximum(cells_in, 1), cells_in


def flow_velocity(
    fields: FlowField | Sequence[FlowField] | None,
    boxes: np.ndarray,
    how: str,
    std_floor: float,
    min_validity: float,
    reach_fraction: float,
) -> FlowVelocity:
    """Boxes [N, 5] (ego metres of the flow's newest scan) -> what the flow says of their velocities: `how` "centre"
    (candidate a) or "box" (candidate b; a box holding no cell centre reads its centre). A sample is used when the
    mean validity behind it reaches `min_validity` and it is not saturated. With several fields (the tiles of a
    mosaic), each box reads the one whose cells measured it best (highest mean validity)."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 5)
    count = len(boxes)
    velocity = np.full((count, 2), np.nan)
    variance = np.full(count, np.nan)
    best = np.zeros(count)
    saturated = np.zeros(count, bool)
    if fields is None or count == 0:
        return FlowVelocity(velocity, variance, best, saturated)
    for field in [fields] if isinstance(fields, FlowField) else list(fields):
        if not field.usable():
            continue
        near = np.flatnonzero(_near_grid(field.grid, boxes))  # boxes whose centre this grid may hold
        if len(near) == 0:
            continue
        picked = boxes[near]
        prepared = _prepared(field)
        if how == "box":
            flow, spread, validity, cells = sample_box(field, picked, prepared=prepared)
            if (cells == 0).any():  # a box holding no cell centre reads its centre
                empty = cells == 0
                flow[empty], validity[empty] = sample_centre(field, picked[empty, :2], prepared)
                spread[empty] = 0.0
        else:
            flow, validity = sample_centre(field, picked[:, :2], prepared)
            spread = np.zeros(len(picked))
        better = validity > best[near]
        index = near[better]
        limit = np.inf if field.reach_m is None else reach_fraction * field.reach_m
        # validity = the share of the full reach the cells were searched over: their limit shrinks with it
        saturated[index] = np.hypot(flow[better, 0], flow[better, 1]) >= limit * validity[better]
        velocity[index] = flow[better] / field.interval_s
        variance[index] = spread[better] ** 2 / field.interval_s**2 + std_floor**2
        best[index] = validity[better]
    unusable = (best < min_validity) | (best <= 0) | saturated
    velocity[unusable] = np.nan
    variance[unusable] = np.nan
    return FlowVelocity(velocity, variance, best, saturated)


def _near_grid(grid: FlowGrid, boxes: np.ndarray) -> np.ndarray:
    """[N] bool: the box centre lies within a cell of the grid's cells (so some cell can measure it)."""
    cells = grid.cells_of(boxes[:, :2])
    return (cells[:, 0] > -1.0) & (cells[:, 0] < grid.shape[0]) & (cells[:, 1] > -1.0) & (cells[:, 1] < grid.shape[1])
