"""The whole view: what a stream detects over, and one frame of it through a streaming runner (numpy only).

One implementation for the service and `rafd eval --full-scan`: a posted scan is covered by the model's S x S
input as tiles, stepped together as the views of one stream state (rafd.runtime), and merged back at tile borders.

Tiles (TileGrid): n x n tiles of side S over the COVERED square (side C, centred on the radar), centres at offsets
(i - (n - 1) / 2) * stride pixels from the radar (stride < S, so neighbours overlap by S - stride pixels), covering it
exactly: (n - 1) * stride + S = C. A tile is a crop whose centre is not the radar: its frame is the ego frame shifted
by the tile's offset (same axes), so its world pose is pose o (offset, 0), and every relative pose between two scans
is the motion of that shifted frame (tile_poses).

View: the covered square is the whole posted scan, or the square of the fewest tiles holding the disc within
`range_m` of the radar (RAFD_DETECT_RANGE_M), at least S: a scan of the model's size is one tile, as the model was
trained. Only tiles
whose centre lies in the covered disc (the scan's inscribed circle: the radar's range) are stepped: on a whole 1152 px
scan, 21 of 25 (the four corner tiles lie mostly outside the circle; the part of the disc only they would see, 82-100 m
on the diagonals, 4% of it, is not covered, for 16% of the cost). Detections farther than the disc's radius are not
answered.

Merging: a detection is kept only by the tile whose core holds its centre (the square of side `stride` around the
tile centre, unbounded outwards at the edge), so a vehicle on a border is reported once, by the tile that sees most
around it; a centre-distance suppression between tiles (`merge_distance`) removes what is left near corners. One
tile's own detections are never suppressed: a scan of the model's size is answered as the model answers it. Dense
maps (the flow, its validity) are put together the same way: each cell of the covered square from the tile whose
core holds it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np

from rafd.detections import Detections, answered_mask, decode_detections
from rafd.geometry import RADIATE_RESOLUTION, RADIATE_SCAN_SIZE, rotation_matrix
from rafd.preprocess import to_model_input
from rafd.protocol import as_operating_threshold

if TYPE_CHECKING:
    from rafd.protocol import OperatingThreshold
    from rafd.runtime.streaming import Runner, StepResult, StreamState

DEFAULT_OVERLAP = 32  # pixels shared by neighbouring tiles (5.6 m at RADIATE's resolution)
MERGE_DISTANCE_M = 1.5  # two merged detections closer than this are one vehicle seen by two tiles


@dataclass(frozen=True)
class TileGrid:
    scan_size: int = RADIATE_SCAN_SIZE  # side of the covered square, pixels
    tile: int = 256
    stride: int = 224
    resolution: float = RADIATE_RESOLUTION

    def __post_init__(self) -> None:
        if not 0 < self.stride <= self.tile <= self.scan_size:
            raise ValueError(f"need 0 < stride <= tile <= scan_size, got {self.stride}, {self.tile}, {self.scan_size}")
        if (self.scan_size - self.tile) % self.stride or (self.scan_size - self.tile) % 2:
            raise ValueError(
                f"tiles of {self.tile} px every {self.stride} px do not cover a {self.scan_size} px scan "
                "symmetrically (choose stride dividing scan_size - tile)"
            )

    @classmethod
    def for_model(
        cls,
        input_size: int,
        scan_size: int = RADIATE_SCAN_SIZE,
        overlap: int = DEFAULT_OVERLAP,
        resolution: float = RADIATE_RESOLUTION,
        step: int = 1,
    ) -> TileGrid:
        """The grid of the fewest tiles overlapping by at least `overlap` pixels whose stride is a multiple of `step`
        (the model's output stride, so the tiles' feature cells line up)."""
        span = scan_size - input_size
        if span % (2 * step):
            raise ValueError(f"a {scan_size} px square has no grid of {input_size} px tiles on a {step} px step")
        count = max(1, math.ceil(span / max(input_size - overlap, 1))) if span else 0
        while count and (span % count or (span // count) % step):
            count += 1  # ends at span // step at the latest: a stride of one step
        return cls(scan_size, input_size, span // count if count else input_size, resolution)

    @property
    def per_side(self) -> int:
        return (self.scan_size - self.tile) // self.stride + 1

    @property
    def offsets_px(self) -> np.ndarray:
        """[n*n, 2] tile-centre offsets (du right, dv down) in pixels from the scan centre, row-major."""
        steps = (np.arange(self.per_side) - (self.per_side - 1) / 2.0) * self.stride
        du, dv = np.meshgrid(steps, steps, indexing="xy")
        return np.stack([du.ravel(), dv.ravel()], -1)

    @property
    def offsets_m(self) -> np.ndarray:
        """[n*n, 2] tile-centre offsets (x right, y forward) in metres in the ego frame."""
        px = self.offsets_px
        return np.stack([px[:, 0], -px[:, 1]], -1) * self.resolution

    def crops(self, scan: np.ndarray, tiles: tuple[int, ...] | None = None) -> np.ndarray:
        """uint8 [C, C] covered square -> [V, S, S] crops of `tiles` (all by default), views of the scan."""
        scan = np.asarray(scan)
        if scan.shape != (self.scan_size, self.scan_size):
            raise ValueError(f"expected a {self.scan_size} px scan, got shape {scan.shape}")
        half = self.scan_size // 2 - self.tile // 2
        offsets = self.offsets_px if tiles is None else self.offsets_px[list(tiles)]
        return np.stack(
            [
                scan[half + int(dv) : half + int(dv) + self.tile, half + int(du) : half + int(du) + self.tile]
                for du, dv in offsets
            ]
        )

    def owner(self, xy: np.ndarray) -> np.ndarray:
        """[M, 2] ego metres -> [M] index of the tile whose core holds each point."""
        steps = np.round(np.asarray(xy, np.float64) / (self.stride * self.resolution) + (self.per_side - 1) / 2.0)
        column = np.clip(steps[:, 0], 0, self.per_side - 1).astype(int)
        row = np.clip((self.per_side - 1) - steps[:, 1], 0, self.per_side - 1).astype(int)  # y forward = rows up
        index: np.ndarray = row * self.per_side + column
        return index


def tile_poses(poses: np.ndarray, offsets_m: np.ndarray) -> np.ndarray:
    """World poses [..., 3] of the ego and tile offsets [n, 2] -> [n, ..., 3] world poses of the tiles' frames."""
    poses = np.asarray(poses, np.float64)
    rotation = rotation_matrix(poses[..., 2])  # [..., 2, 2]
    shifted = poses[None, ..., :2] + np.einsum("...ij,nj->n...i", rotation, offsets_m)
    return np.concatenate([shifted, np.broadcast_to(poses[None, ..., 2:], shifted.shape[:-1] + (1,))], -1)


def covering_grid(
    posted_size: int, input_size: int, resolution: float, cell_px: int, range_m: float | None, overlap: int
) -> TileGrid:
    """The tiles a scan is detected over: the whole scan's grid, or the fewest tiles (overlapping by at least
    `overlap` px, their stride a whole number of cells) whose square holds the disc within `range_m` of the radar;
    one tile, the model's input, at least."""
    whole = TileGrid.for_model(input_size, posted_size, overlap, resolution, step=cell_px)
    if range_m is None:
        return whole
    span = max(0.0, 2.0 * range_m / resolution - input_size)  # the tile centres' spread the disc needs
    if span == 0.0:
        return TileGrid(input_size, input_size, input_size, resolution)
    count = math.ceil(span / max(input_size - overlap, 1))
    stride = cell_px * math.ceil(span / count / cell_px)
    side = input_size + count * stride
    return whole if side >= posted_size else TileGrid(side, input_size, stride, resolution)


@dataclass(frozen=True)
class View:
    """The tiles a stream's frames are detected over, the disc they answer for, and the scan they lie in."""

    grid: TileGrid
    tiles: tuple[int, ...]  # the grid's tiles stepped, row-major: those whose centre lies in the covered disc
    range_m: float | None  # detections farther from the radar are not answered (None: all the tiles see)
    posted_size: int  # side of the Cartesian scan posted (or converted from a polar or native one)
    cell_px: int  # pixels per cell of the model's output maps (its output stride)

    @classmethod
    def of(
        cls,
        posted_size: int,
        input_size: int,
        resolution: float,
        cell_px: int,
        range_m: float | None = None,
        overlap: int = DEFAULT_OVERLAP,
    ) -> View:
        grid = covering_grid(posted_size, input_size, resolution, cell_px, range_m, overlap)
        side = grid.scan_size
        radius = side / 2.0 * resolution if range_m is None else min(range_m, side / 2.0 * resolution)
        # a tile is stepped when its centre lies within the disc (a corner tile of a whole scan, mostly outside the
        # radar's circle, is not: its core's share of the disc, 82-100 m on the diagonals, is not covered)
        tiles = tuple(int(t) for t in np.flatnonzero(np.hypot(*grid.offsets_m.T) <= radius + 1e-6))
        return cls(grid, tiles, None if range_m is None else float(radius), int(posted_size), int(cell_px))

    @property
    def tiling(self) -> tuple[TileGrid, tuple[int, ...]]:
        """What a stream's model state is per: the tiles stepped (a chain continues over scans of another posted
        size when they are detected over the same tiles, e.g. a model-size crop and a scan within that range)."""
        return self.grid, self.tiles

    @property
    def side_px(self) -> int:
        return self.grid.scan_size

    @property
    def origin_px(self) -> int:
        """Posted pixel (u and v) of the covered square's top-left corner."""
        return (self.posted_size - self.side_px) // 2

    @property
    def offsets_m(self) -> np.ndarray:
        """[V, 2] the stepped tiles' centres, ego metres."""
        return self.grid.offsets_m[list(self.tiles)]

    def crops(self, covered: np.ndarray) -> np.ndarray:
        """uint8 [C, C] covered square -> float32 [V, S, S] model inputs of the stepped tiles."""
        return to_model_input(np.ascontiguousarray(self.grid.crops(covered, self.tiles)))

    def tile_poses(self, pose: np.ndarray) -> np.ndarray:
        """The ego's world pose [3] -> [V, 3] the stepped tiles' world poses."""
        return tile_poses(np.asarray(pose, np.float64)[None], self.offsets_m)[:, 0]

    def merge(
        self,
        boxes: np.ndarray,
        scores: np.ndarray,
        score_threshold: OperatingThreshold | float = 0.0,
        merge_distance: float = MERGE_DISTANCE_M,
    ) -> Detections:
        """The stepped tiles' outputs (boxes [V, K, 5] in each tile's frame, scores [V, K]) -> detections in the ego
        frame within the view's range that the threshold answers (at each one's range from the radar), best first:
        each from the tile whose core holds it, one per vehicle."""
        lowest = as_operating_threshold(score_threshold).lowest
        kept_boxes, kept_scores, kept_labels, kept_tiles = [], [], [], []
        for tile, tile_boxes, tile_scores in zip(self.tiles, boxes, scores):
            found = decode_detections(tile_boxes, tile_scores, lowest)
            ego = found.boxes.copy()
            ego[:, :2] += self.grid.offsets_m[tile]
            mine = (self.grid.owner(ego[:, :2]) == tile) & answered_mask(ego[:, :2], found.scores, score_threshold)
            if self.range_m is not None:
                mine &= np.hypot(ego[:, 0], ego[:, 1]) <= self.range_m
            kept_boxes.append(ego[mine])
            kept_scores.append(found.scores[mine])
            kept_labels.append(found.labels[mine])
            kept_tiles.append(np.full(int(mine.sum()), tile))
        merged_boxes, merged_scores = np.concatenate(kept_boxes).reshape(-1, 5), np.concatenate(kept_scores)
        merged_labels, merged_tiles = np.concatenate(kept_labels), np.concatenate(kept_tiles)
        order = np.argsort(-merged_scores, kind="stable")
        centres, tiles = merged_boxes[order, :2], merged_tiles[order]
        distance = np.hypot(*(centres[:, None] - centres[None]).transpose(2, 0, 1))  # [N, N] metres
        conflict = (distance <= merge_distance) & (tiles[:, None] != tiles[None])  # [N, N]
        kept = np.zeros(len(order), bool)
        for i in range(len(order)):  # best first: drop what another tile saw near a kept detection
            kept[i] = not (conflict[i] & kept).any()
        keep = order[kept]
        return Detections(merged_boxes[keep], merged_scores[keep], merged_labels[keep])

    @cached_property
    def _cells(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For every cell of the covered square: the stepped view whose core holds it (-1: none) and its row and
        column in that view's map."""
        cells = self.side_px // self.cell_px
        centres = (np.arange(cells) + 0.5) * self.cell_px  # pixel coordinates along one side
        u, v = np.meshgrid(centres, centres, indexing="xy")  # [H, W]
        half = self.side_px / 2.0
        xy = np.stack([(u - half).ravel(), (half - v).ravel()], -1) * self.grid.resolution
        owner = self.grid.owner(xy).reshape(cells, cells)  # [H, W] grid tile index
        view = np.full(self.grid.per_side**2, -1)
        view[list(self.tiles)] = np.arange(len(self.tiles))
        origin = self.side_px // 2 - self.grid.tile // 2 + self.grid.offsets_px[owner]  # [H, W, 2] tile top-left
        column = ((u - origin[..., 0]) // self.cell_px).astype(np.intp)
        row = ((v - origin[..., 1]) // self.cell_px).astype(np.intp)
        return view[owner], row, column

    def mosaic(self, maps: np.ndarray) -> np.ndarray:
        """[V, ..., h, w] per-view maps (h = w = S / cell_px) -> [..., H, W] over the covered square (H = C / cell_px),
        each cell from the view whose core holds it; 0 where no view was stepped."""
        view, row, column = self._cells
        out = np.asarray(maps)[np.maximum(view, 0), ..., row, column]  # [H, W, ...]
        out = np.moveaxis(out, (0, 1), (-2, -1))
        return np.where(view >= 0, out, 0).astype(maps.dtype)


def step_view(
    runner: Runner, state: StreamState, view: View, covered: np.ndarray, pose: np.ndarray
) -> tuple[StepResult, StreamState]:
    """One frame of a stream over its view: the covered square (uint8 [C, C]) and the ego's world pose [3] -> (each
    stepped tile's result, the stream's new state), every tile in one run of the runner."""
    return runner.step(state, view.crops(covered), view.tile_poses(pose))
