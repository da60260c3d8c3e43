"""Window dicts from the dataset -> one batch of tensors (targets built per window by rafd.data.targets)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from rafd.config import RaFDConfig
from rafd.data.targets import build_targets
from rafd.preprocess import to_model_input


@dataclass
class Batch:
    frames: Tensor  # [B, T, 1, H, W] float in [0, 1], oldest first
    poses: Tensor  # [B, T, 3] world poses (x, y, yaw)
    targets: dict[str, Tensor]  # rafd.data.targets.build_targets keys, each with a leading batch dim
    boxes: list[np.ndarray] = field(default_factory=list)  # per window [M, 5]: ALL GT boxes of the newest frame
    ignore: list[np.ndarray] = field(default_factory=list)  # per window [K, 5]: the newest frame's ignore regions
    sequences: list[str] = field(default_factory=list)
    frame_numbers: list[int] = field(default_factory=list)  # newest frame's RADIATE number per window

    def __len__(self) -> int:
        return int(self.frames.shape[0])

    def pin_memory(self) -> Batch:
        """Page-locked copies (DataLoader(pin_memory=True) calls this), so .to(cuda, non_blocking=True) overlaps."""
        return Batch(
            frames=self.frames.pin_memory(),
            poses=self.poses.pin_memory(),
            targets={k: v.pin_memory() for k, v in self.targets.items()},
            boxes=self.boxes,
            ignore=self.ignore,
            sequences=self.sequences,
            frame_numbers=self.frame_numbers,
        )

    def to(self, device: torch.device) -> Batch:
        return Batch(
            frames=self.frames.to(device, non_blocking=True),
            poses=self.poses.to(device, non_blocking=True),
            targets={k: v.to(device, non_blocking=True) for k, v in self.targets.items()},
            boxes=self.boxes,
            ignore=self.ignore,
            sequences=self.sequences,
            frame_numbers=self.frame_numbers,
        )


def _frames_tensor(frames: Any, where: str) -> Tensor:
    """Window frames [T, H, W] or [T, 1, H, W] (uint8 or float) -> float32 [T, 1, H, W] in [0, 1]."""
    array = np.asarray(frames)
    if array.ndim == 3:
        array = array[:, None]  # [T, 1, H, W]
    if array.ndim != 4 or array.shape[1] != 1:
        raise ValueError(f"{where}: frames must be [T, H, W] or [T, 1, H, W], got {tuple(array.shape)}")
    if array.dtype == np.uint8:
        return torch.from_numpy(to_model_input(array))
    return torch.as_tensor(array).float()


def window_targets(window: dict[str, Any], cfg: RaFDConfig) -> dict[str, np.ndarray]:
    """One window's detection (newest frame) and flow (every consecutive pair) targets."""
    boxes = [np.asarray(b, dtype=np.float64).reshape(-1, 5) for b in window["boxes"]]
    ids = [np.asarray(i, dtype=np.int64).reshape(-1) for i in window["ids"]]
    ignore = window.get("ignore")
    newest_ignore = None if ignore is None else np.asarray(ignore[-1], dtype=np.float64).reshape(-1, 5)
    return build_targets(boxes, ids, np.asarray(window["poses"], dtype=np.float64), cfg, newest_ignore)


class Collator:
    """Picklable collate_fn: builds targets per window and stacks (DataLoader workers may run it)."""

    def __init__(self, cfg: RaFDConfig) -> None:
        self.cfg = cfg

    def __call__(self, windows: Sequence[dict[str, Any]]) -> Batch:
        if not windows:
            raise ValueError("cannot collate an empty list of windows")
        frames, poses, boxes, ignore, sequences, numbers = [], [], [], [], [], []
        targets: dict[str, list[np.ndarray]] = {}
        for index, window in enumerate(windows):
            where = f"window {index} ({window.get('sequence', '?')})"
            frame_tensor = _frames_tensor(window["frames"], where)
            if frame_tensor.shape[0] != self.cfg.num_frames:
                raise ValueError(f"{where}: {frame_tensor.shape[0]} frames, the config expects {self.cfg.num_frames}")
            frames.append(frame_tensor)
            poses.append(torch.as_tensor(np.asarray(window["poses"], dtype=np.float32)))  # [T, 3]
            for key, value in window_targets(window, self.cfg).items():
                targets.setdefault(key, []).append(value)
            boxes.append(np.asarray(window["boxes"][-1], dtype=np.float64).reshape(-1, 5))
            regions = window.get("ignore")
            ignore.append(np.zeros((0, 5)) if regions is None else np.asarray(regions[-1], np.float64).reshape(-1, 5))
            sequences.append(str(window.get("sequence", "")))
            numbers.append(int(window.get("frame", -1)))
        return Batch(
            frames=torch.stack(frames),  # [B, T, 1, H, W]
            poses=torch.stack(poses),  # [B, T, 3]
            targets={k: torch.from_numpy(np.stack(v)) for k, v in targets.items()},
            boxes=boxes,
            ignore=ignore,
            sequences=sequences,
            frame_numbers=numbers,
        )
