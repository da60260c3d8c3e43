"""Window-consistent augmentation: mirror (x -> -x) and rotation about the radar, and radar intensity changes.

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

Tile shift (AugmentConfig.shift_max_m > 0): the crop is cut around a point away from the radar, as the full-scan
tiles of rafd.eval.tiled are, so a model also learns what vehicles at 50-90 m look like. The crop's frame is the ego
frame
shifted by `shift_m` (whole pixels): boxes and points move by -shift_m and poses become the shifted frame's world
poses (pose o (shift_m, 0)), before the flip/rotation, which then turns about the crop's centre.

Intensity (Augmentation.intensity, off unless AugmentConfig.intensity_probability > 0): what another receiver gain,
weather or sensor does to the grey levels, applied to the cropped uint8 frames, the same for the whole window (up to a
small per-frame gain jitter): g = gain * jitter_t * (grey / 255) ** gamma, a speckled floor added in power,
sqrt(g^2 + (floor / 255)^2 E) with E ~ Exp(1) per pixel, then a Gaussian blur (coarser speckle and point spread).
Boxes, poses and flow are unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np

from rafd.geometry import RADIATE_RESOLUTION, rotation_matrix, wrap_angle
from rafd.preprocess import model_crop, rotation_crop


@dataclass(frozen=True)
class AugmentConfig:
    enabled: bool = True  # False: every window as recorded (the values below are then unused)
    flip_probability: float = 0.5  # chance of mirroring x -> -x
    max_rotation_deg: float = 15.0  # rotation angle uniform in +-this (0 disables rotation)
    intensity_probability: float = 0.0  # chance a window's intensities change (0: geometry only)
    gain_range: tuple[float, float] = (0.6, 1.6)  # grey levels scale by a log-uniform factor in this range
    gamma_range: tuple[float, float] = (0.8, 1.25)  # log-uniform
    floor_max: float = 14.0  # grey level of the speckled floor added in power (uniform in [0, this])
    blur_max: float = 0.9  # pixels: Gaussian blur sigma (uniform in [0, this])
    frame_gain_jitter: float = 0.05  # per-frame gain factor exp(N(0, this)) within a window
    shift_probability: float = 0.0  # chance a window is cut away from the radar (a full-scan tile)
    shift_max_m: float = 0.0  # the crop's centre lies uniformly in a disc of this radius around the radar

    def __post_init__(self) -> None:
        if not 0.0 <= self.intensity_probability <= 1.0:
            raise ValueError(f"intensity_probability must be in [0, 1], got {self.intensity_probability}")
        for name in ("gain_range", "gamma_range"):
            lo, hi = getattr(self, name)
            if not 0.0 < lo <= hi:
                raise ValueError(f"{name} must be (lo, hi) with 0 < lo <= hi, got {(lo, hi)}")
        if self.floor_max < 0 or self.blur_max < 0 or self.frame_gain_jitter < 0:
            raise ValueError("floor_max, blur_max and frame_gain_jitter must be >= 0")
        if not 0.0 <= self.shift_probability <= 1.0 or self.shift_max_m < 0:
            raise ValueError("shift_probability must be in [0, 1] and shift_max_m >= 0")
        if not 0.0 <= self.flip_probability <= 1.0:
            raise ValueError(f"flip_probability must be in [0, 1], got {self.flip_probability}")
        if not (math.isfinite(self.max_rotation_deg) and 0.0 <= self.max_rotation_deg <= 180.0):
            raise ValueError(f"max_rotation_deg must be in [0, 180], got {self.max_rotation_deg}")


@dataclass(frozen=True)
class Augmentation:
    flip: bool = False  # mirror x -> -x first
    angle: float = 0.0  # then rotate counter-clockwise (ego metres) about the radar, radians
    gain: float = 1.0  # intensity (see the module docstring); all at their neutral values = no change
    gamma: float = 1.0
    floor: float = 0.0  # grey
    blur: float = 0.0  # pixels
    jitter: float = 0.0  # per-frame gain jitter sigma
    noise_seed: int = 0  # the floor's speckle and the jitter are drawn from this
    shift_px: tuple[int, int] = (0, 0)  # crop centre (right, down) in pixels from the radar
    shift_m: tuple[float, float] = (0.0, 0.0)  # the same in ego metres (x right, y forward)

    @classmethod
    def sample(
        cls, rng: np.random.Generator, config: AugmentConfig = AugmentConfig(), resolution: float = RADIATE_RESOLUTION
    ) -> Augmentation:
        flip = bool(rng.random() < config.flip_probability)
        limit = math.radians(config.max_rotation_deg)
        angle = float(rng.uniform(-limit, limit)) if limit > 0 else 0.0
        shift: dict = {}
        if config.shift_max_m > 0 and rng.random() < config.shift_probability:
            radius, direction = config.shift_max_m * math.sqrt(rng.random()), rng.uniform(0, 2 * math.pi)
            du, dv = (int(round(v / resolution)) for v in (radius * math.cos(direction), -radius * math.sin(direction)))
            shift = {"shift_px": (du, dv), "shift_m": (du * resolution, -dv * resolution)}
        if not rng.random() < config.intensity_probability:
            return cls(flip=flip, angle=angle, **shift)
        log_uniform = lambda lo_hi: float(math.exp(rng.uniform(math.log(lo_hi[0]), math.log(lo_hi[1]))))  # noqa: E731
        return cls(
            flip=flip,
            angle=angle,
            gain=log_uniform(config.gain_range),
            gamma=log_uniform(config.gamma_range),
            floor=float(rng.uniform(0.0, config.floor_max)),
            blur=float(rng.uniform(0.0, config.blur_max)),
            jitter=config.frame_gain_jitter,
            noise_seed=int(rng.integers(2**31)),
            **shift,
        )

    @property
    def changes_intensity(self) -> bool:
        return (self.gain, self.gamma, self.floor, self.blur, self.jitter) != (1.0, 1.0, 0.0, 0.0, 0.0)

    def as_dict(self) -> dict[str, float | bool | tuple[float, float]]:
        """The parameters (what a window records of its augmentation)."""
        return {
            "flip": self.flip,
            "angle": self.angle,
            "gain": self.gain,
            "gamma": self.gamma,
            "floor": self.floor,
            "blur": self.blur,
            "shift_px": self.shift_px,
            "shift_m": self.shift_m,
        }

    def intensity(self, frames: np.ndarray) -> np.ndarray:
        """uint8 [T, S, S] window frames -> the same frames under this augmentation's intensity change."""
        frames = np.asarray(frames)
        if not self.changes_intensity:
            return frames
        rng = np.random.default_rng(self.noise_seed)
        gains = self.gain * np.exp(rng.normal(0.0, self.jitter, len(frames)))
        out = np.empty(frames.shape, np.uint8)
        for t, frame in enumerate(frames):
            grey = gains[t] * (frame.astype(np.float32) / 255.0) ** self.gamma
            if self.floor > 0:
                floor = (self.floor / 255.0) ** 2 * rng.standard_exponential(frame.shape).astype(np.float32)
                grey = np.sqrt(grey * grey + floor)
            if self.blur > 0:
                grey = cv2.GaussianBlur(grey, (0, 0), self.blur)
            out[t] = np.clip(np.rint(grey * 255.0), 0, 255)
        return out

    @cached_property
    def matrix(self) -> np.ndarray:
        """[2, 2] G acting on ego metres."""
        mirror = np.diag([-1.0, 1.0]) if self.flip else np.eye(2)
        return rotation_matrix(self.angle) @ mirror

    def _yaw(self, yaw: np.ndarray) -> np.ndarray:
        return -yaw if self.flip else yaw

    def points(self, points: np.ndarray) -> np.ndarray:
        """[..., 2] ego metres -> [..., 2] in the augmented crop's frame."""
        return (np.asarray(points, dtype=np.float64) - np.asarray(self.shift_m)) @ self.matrix.T

    def vectors(self, vectors: np.ndarray) -> np.ndarray:
        """[..., 2] displacements (flow) -> [..., 2]: turned and mirrored, not shifted."""
        return np.asarray(vectors, dtype=np.float64) @ self.matrix.T

    def boxes(self, boxes: np.ndarray) -> np.ndarray:
        """[N, 5] (x, y, width, length, yaw) -> [N, 5]."""
        boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 5)
        out = boxes.copy()
        out[:, :2] = self.points(boxes[:, :2])
        out[:, 4] = wrap_angle(self.angle + self._yaw(boxes[:, 4]))
        return out

    def poses(self, poses: np.ndarray) -> np.ndarray:
        """[T, 3] world poses -> [T, 3] world poses of the crop's (shifted) frame in the transformed world (relative
        motions map by G)."""
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        out = poses.copy()
        shifted = poses[:, :2] + np.einsum("tij,j->ti", rotation_matrix(poses[:, 2]), np.asarray(self.shift_m))
        out[:, :2] = self.vectors(shifted)  # the world turns and mirrors like displacements (no shift)
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
        if self.shift_px != (0, 0):  # re-centre on the shifted point: the largest square around it
            du, dv = self.shift_px
            side = height - 2 * max(abs(du), abs(dv))
            if side < size:
                raise ValueError(f"a crop {self.shift_px} px from the centre of a {height} px scan leaves {side} px")
            top, left = (height - side) // 2 + dv, (height - side) // 2 + du
            image, height = image[top : top + side, left : left + side], side
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
            image,
            warp,
            (size, size),
            flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
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
