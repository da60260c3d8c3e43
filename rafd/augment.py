"""Window-consistent geometric augmentation: mirror (x -> -x) and rotation about the radar.

One `Augmentation` is drawn per window and applied identically to every frame, so images, boxes, poses and
therefore the pseudo-GT flow built from them stay consistent. It acts on ego coordinates as the linear map
G = R(angle) @ M with M = diag(-1, 1) when flipped (identity otherwise):
- points / box centres: q' = G q;
- boxes: size unchanged; yaw' = angle + (-yaw if flipped else yaw) (a mirror reverses the box's
  orientation: M R(yaw) = R(-yaw) M, and M maps the box's corner set onto itself);
- poses: the world frame is transformed by the same G, so pose' = (G (x, y), -yaw if flipped else yaw).
  Then every relative pose maps like a point displacement: relative' = (G t, +-dyaw), object motion with
  ego motion removed becomes G times the original, and flow' (G q) = G flow(q);
- images: the scan is resampled so that the content at ego position q appears at G q, radar fixed.

Images are transformed BEFORE cropping, straight from the full scan into the S x S crop with one
cv2.warpAffine (bilinear, zeros outside the scan): a rotated crop is filled with real scan content
whenever the full scan is at least S * sqrt(2) wide (RADIATE 1152 >= 362 for S = 256). Pure flips and the
identity are exact pixel copies. The crop protocol (centre inside the crop) is applied afterwards to the
transformed boxes, by rafd.data.dataset.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np

from rafd.geometry import rotation_matrix, wrap_angle
from rafd.preprocess import model_crop, rotation_crop


@dataclass(frozen=True)
class AugmentConfig:
    flip_probability: float = 0.5  # chance of mirroring x -> -x
    max_rotation_deg: float = 15.0  # rotation angle uniform in +-this (0 disables rotation)

    def __post_init__(self) -> None:
        if not 0.0 <= self.flip_probability <= 1.0:
            raise ValueError(f"flip_probability must be in [0, 1], got {self.flip_probability}")
        if not (math.isfinite(self.max_rotation_deg) and 0.0 <= self.max_rotation_deg <= 180.0):
            raise ValueError(f"max_rotation_deg must be in [0, 180], got {self.max_rotation_deg}")


@dataclass(frozen=True)
class Augmentation:
    flip: bool = False  # mirror x -> -x first
    angle: float = 0.0  # then rotate counter-clockwise (ego metres) about the radar, radians

    @classmethod
    def sample(cls, rng: np.random.Generator, config: AugmentConfig = AugmentConfig()) -> "Augmentation":
        flip = bool(rng.random() < config.flip_probability)
        limit = math.radians(config.max_rotation_deg)
        angle = float(rng.uniform(-limit, limit)) if limit > 0 else 0.0
        return cls(flip=flip, angle=angle)

    @property
    def is_identity(self) -> bool:
        return not self.flip and self.angle == 0.0

    @cached_property
    def matrix(self) -> np.ndarray:
        """[2, 2] G acting on ego metres."""
        mirror = np.diag([-1.0, 1.0]) if self.flip else np.eye(2)
        return rotation_matrix(self.angle) @ mirror

    def _yaw(self, yaw: np.ndarray) -> np.ndarray:
        return -yaw if self.flip else yaw

    def points(self, points: np.ndarray) -> np.ndarray:
        """[..., 2] ego metres (or displacement vectors) -> [..., 2]."""
        return np.asarray(points, dtype=np.float64) @ self.matrix.T

    def boxes(self, boxes: np.ndarray) -> np.ndarray:
        """[N, 5] (x, y, width, length, yaw) -> [N, 5]."""
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 5)
        out = boxes.copy()
        out[:, :2] = self.points(boxes[:, :2])
        out[:, 4] = wrap_angle(self.angle + self._yaw(boxes[:, 4]))
        return out

    def poses(self, poses: np.ndarray) -> np.ndarray:
        """[T, 3] world poses -> [T, 3] in the transformed world (relative motions map by G)."""
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        out = poses.copy()
        out[:, :2] = self.points(poses[:, :2])
        out[:, 2] = wrap_angle(self._yaw(poses[:, 2]))
        return out

    def image(self, image: np.ndarray, size: int | None = None) -> np.ndarray:
        """[H, H] scan (radar at the centre) -> [size, size] transformed centre crop (size None = H)."""
        height = image.shape[0]
        size = height if size is None else int(size)
        if image.ndim != 2 or image.shape[1] != height:
            raise ValueError(f"expected a square 2-D scan, got shape {image.shape}")
        if size > height:
            raise ValueError(f"cannot crop {size}x{size} from a {height}x{height} scan")
        if self.angle == 0.0:
            crop = model_crop(image, size)
            return np.ascontiguousarray(crop[:, ::-1]) if self.flip else crop.copy()
        # Warp from the smallest crop that holds every turned output pixel: the same source whether the scan is a
        # full 1152 px scan or a prepared cache crop, so both give bit-identical windows.
        image = model_crop(image, min(height, rotation_crop(size) + (height - rotation_crop(size)) % 2))
        height = image.shape[0]
        # cv2 pixel indices d of the output: source index = A (d - c_out) + c_in with A = M G^-1 M (M flips
        # image v: metres y points up). Derivation in the module docstring's conventions.
        flip_v = np.diag([1.0, -1.0])
        a = flip_v @ np.linalg.inv(self.matrix) @ flip_v
        c_out, c_in = (size - 1) / 2.0, (height - 1) / 2.0
        b = np.array([c_in, c_in]) - a @ np.array([c_out, c_out])
        warp = np.concatenate([a, b[:, None]], 1)
        return cv2.warpAffine(
            image, warp, (size, size), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_CONSTANT, borderValue=0
        )

    def flow(self, flow: np.ndarray) -> np.ndarray:
        """[..., 2, Hf, Wf] flow maps -> transformed maps. Exact for flips and multiples of 90 degrees (the
        grid maps onto itself); other angles are not supported (rebuild the targets from transformed boxes)."""
        quarter = self.angle / (math.pi / 2.0)
        if abs(quarter - round(quarter)) > 1e-9:
            raise ValueError("flow maps can only be transformed exactly for flips and multiples of 90 degrees")
        flow = np.asarray(flow)
        vectors = np.moveaxis(flow, -3, -1) @ self.matrix.T.astype(flow.dtype)  # [..., Hf, Wf, 2]
        grid = _grid(vectors, self.flip, int(round(quarter)) % 4)
        return np.ascontiguousarray(np.moveaxis(grid, -1, -3))

    def grid(self, maps: np.ndarray) -> np.ndarray:
        """[..., Hf, Wf] scalar maps (heatmaps, masks) -> transformed maps (flips and 90 degree multiples)."""
        quarter = self.angle / (math.pi / 2.0)
        if abs(quarter - round(quarter)) > 1e-9:
            raise ValueError("grid maps can only be transformed exactly for flips and multiples of 90 degrees")
        return np.ascontiguousarray(_grid(np.asarray(maps)[..., None], self.flip, int(round(quarter)) % 4)[..., 0])


def _grid(maps: np.ndarray, flip: bool, quarters: int) -> np.ndarray:
    """[..., H, W, C]: content at cell (row, col) moved to where G puts it (mirror columns, then turn CCW)."""
    if flip:
        maps = maps[..., :, ::-1, :]
    # A counter-clockwise turn in ego metres (y up) is a counter-clockwise turn of the image: np.rot90 over (H, W).
    return np.rot90(maps, k=quarters, axes=(-3, -2))
