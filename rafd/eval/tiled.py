"""Full-scan detection by tiles: the model's S x S input slid over a whole 1152 px scan, merged at tile borders.

Tiles: n x n tiles of the model's input size S, centres at offsets (i - (n - 1) / 2) * stride pixels from the radar
(stride < S, so neighbours overlap by S - stride pixels), covering the scan exactly when (n - 1) * stride + S = N.
A tile is a crop whose centre is not the radar: its frame is the ego frame shifted by the tile's offset, so its
world pose is pose o (offset, 0) and every relative pose between two scans is the motion of that shifted frame
(tile_poses). Streaming keeps one state per tile (TiledStream).

Merging: a detection is kept only by the tile whose core holds its centre (the core is the square of side `stride`
around the tile centre, unbounded outwards at the scan's edge), so a vehicle on a border is reported once, by the
tile that sees most around it; a centre-distance suppression (`merge_distance`) removes what is left near corners.
Everything here is numpy; the model call is a function the caller passes (PyTorch or onnxruntime).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from rafd.detections import Detections, decode_detections
from rafd.geometry import RADIATE_RESOLUTION, RADIATE_SCAN_SIZE, rotation_matrix

DEFAULT_OVERLAP = 32  # pixels shared by neighbouring tiles (5.6 m)


@dataclass(frozen=True)
class TileGrid:
    scan_size: int = RADIATE_SCAN_SIZE
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
    ) -> TileGrid:
        """The grid of the fewest tiles overlapping by at least `overlap` pixels."""
        span = scan_size - input_size
        count = max(1, math.ceil(span / max(input_size - overlap, 1))) if span else 0
        while count and span % count:
            count += 1
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

    def crops(self, scan: np.ndarray) -> np.ndarray:
        """uint8 [N, N] scan -> [n*n, S, S] tile crops (views of the scan)."""
        scan = np.asarray(scan)
        if scan.shape != (self.scan_size, self.scan_size):
            raise ValueError(f"expected a {self.scan_size} px scan, got shape {scan.shape}")
        half = self.scan_size // 2 - self.tile // 2
        return np.stack(
            [
                scan[half + int(dv) : half + int(dv) + self.tile, half + int(du) : half + int(du) + self.tile]
                for du, dv in self.offsets_px
            ]
        )

    def owner(self, xy: np.ndarray) -> np.ndarray:
        """[M, 2] ego metres -> [M] index of the tile whose core holds each point."""
        steps = np.round(np.asarray(xy, np.float64) / (self.stride * self.resolution) + (self.per_side - 1) / 2.0)
        column = np.clip(steps[:, 0], 0, self.per_side - 1).astype(int)
        row = np.clip((self.per_side - 1) - steps[:, 1], 0, self.per_side - 1).astype(int)  # y forward = rows up
        return row * self.per_side + column


def tile_poses(poses: np.ndarray, offsets_m: np.ndarray) -> np.ndarray:
    """World poses [..., 3] of the ego and tile offsets [n, 2] -> [n, ..., 3] world poses of the tiles' frames."""
    poses = np.asarray(poses, np.float64)
    rotation = rotation_matrix(poses[..., 2])  # [..., 2, 2]
    shifted = poses[None, ..., :2] + np.einsum("...ij,nj->n...i", rotation, offsets_m)
    return np.concatenate([shifted, np.broadcast_to(poses[None, ..., 2:], shifted.shape[:-1] + (1,))], -1)


def merge_tiles(
    grid: TileGrid, boxes: np.ndarray, scores: np.ndarray, score_threshold: float = 0.0, merge_distance: float = 1.5
) -> Detections:
    """Per-tile outputs (boxes [n*n, K, 5] in each tile's frame, scores [n*n, K]) -> detections in the ego frame."""
    offsets = grid.offsets_m
    kept_boxes, kept_scores = [], []
    for index, (tile_boxes, tile_scores) in enumerate(zip(boxes, scores)):
        found = decode_detections(tile_boxes, tile_scores, score_threshold)
        ego = found.boxes.copy()
        ego[:, :2] += offsets[index]
        mine = grid.owner(ego[:, :2]) == index
        kept_boxes.append(ego[mine])
        kept_scores.append(found.scores[mine])
    merged = decode_detections(np.concatenate(kept_boxes).reshape(-1, 5), np.concatenate(kept_scores), score_threshold)
    keep: list[int] = []
    for i in range(len(merged)):  # best first: drop anything within merge_distance of a kept detection
        if all(np.hypot(*(merged.boxes[i, :2] - merged.boxes[j, :2])) > merge_distance for j in keep):
            keep.append(i)
    return Detections(merged.boxes[keep], merged.scores[keep], merged.labels[keep])


def detect_windows(
    grid: TileGrid,
    scans: Sequence[np.ndarray],
    poses: np.ndarray,
    model: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]],
    score_threshold: float = 0.0,
) -> Detections:
    """One window of full scans (T x uint8 [N, N], oldest first) and world poses [T, 3] -> merged detections of the
    newest scan. `model(frames uint8 [n*n, T, S, S], poses [n*n, T, 3]) -> (boxes [n*n, K, 5], scores [n*n, K])`."""
    crops = np.stack([grid.crops(scan) for scan in scans], axis=1)  # [n*n, T, S, S]
    boxes, scores = model(crops, tile_poses(poses, grid.offsets_m))
    return merge_tiles(grid, np.asarray(boxes), np.asarray(scores), score_threshold)


class TiledStream:
    """A stream of full scans through a streaming runner (rafd.runtime): the tiles step together as the views of
    one stream state."""

    def __init__(self, runner, grid: TileGrid | None = None) -> None:
        from rafd.preprocess import to_model_input

        self.runner = runner
        cfg = runner.config
        self.grid = grid or TileGrid.for_model(cfg.input_size, resolution=cfg.resolution)
        if self.grid.tile != cfg.input_size:
            raise ValueError(f"tiles of {self.grid.tile} px for a model of {cfg.input_size} px")
        self._to_input = to_model_input
        self.state = runner.new_state()

    def step(self, scan: np.ndarray, pose: np.ndarray, score_threshold: float = 0.0) -> Detections:
        """Add one full scan with its world pose -> its merged detections (ego frame)."""
        crops = self._to_input(np.ascontiguousarray(self.grid.crops(scan)))  # [n*n, S, S]
        poses = tile_poses(np.asarray(pose, np.float64)[None], self.grid.offsets_m)[:, 0]  # [n*n, 3]
        result, self.state = self.runner.step(self.state, crops, poses)
        return merge_tiles(self.grid, result.boxes, result.scores, score_threshold)
