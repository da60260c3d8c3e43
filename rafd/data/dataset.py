"""Windows of T consecutive radar frames under the benchmark protocol (a torch Dataset).

Protocol (TempoRadar / SIRA / RaFD on RADIATE): centre crop to cfg.input_size around the radar, objects
whose centre falls outside the crop dropped, pedestrian and group_of_pedestrians dropped, every other
class merged into `vehicle` (the window keeps the original class names in "classes").

Sequences: every folder holding Navtech_Cartesian/ under `root` (or `root` itself), filtered by meta.json
"set" == split (exact match; a list of splits is also accepted; None = all). Each sequence's metadata
(frames, timestamps, boxes, ids, poses) is read once at construction and kept in memory; images are read
lazily per window (with a small per-process cache of decoded scans: consecutive windows share T-1 frames).

Augmentation (augment=True or an AugmentConfig): one rafd.augment.Augmentation per window, drawn from a
generator seeded by (seed, DataLoader worker seed, index, draw count), applied to the full scans before the
crop and to boxes and poses; the crop protocol is applied to the augmented boxes.
"""
from __future__ import annotations

import logging
import os
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from rafd.augment import AugmentConfig, Augmentation
from rafd.config import RaFDConfig
from rafd.data.reader import IMAGE_DIR, POLAR_DIR, load_image, read_sequence
from rafd.geometry import metres_to_pixels

try:  # a torch Dataset when torch is installed (DataLoader works with any __getitem__/__len__ object)
    from torch.utils.data import Dataset as _Base
except ImportError:  # pragma: no cover - torch-free installs
    _Base = object  # type: ignore[assignment,misc]

log = logging.getLogger(__name__)

DROPPED_CLASSES = frozenset({"pedestrian", "group_of_pedestrians"})
MERGED_CLASS = "vehicle"
IMAGE_CACHE_SIZE = 8  # decoded full scans kept per process


def find_sequences(root: str | Path) -> list[Path]:
    """Sequence folders (holding Navtech_Cartesian/, or only the polar scans Navtech_Polar/) at or under `root`,
    sorted; FileNotFoundError if none."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"data root {root} not found or not a directory")
    scan_dirs = {IMAGE_DIR, POLAR_DIR}
    if any((root / name).is_dir() for name in scan_dirs):
        return [root]
    found = []
    for current, folders, _ in os.walk(root):
        if scan_dirs & set(folders):
            found.append(Path(current))
            folders[:] = []  # a sequence folder holds no further sequences
        else:
            folders.sort()
    if not found:
        raise FileNotFoundError(f"no RADIATE sequence folders (with {IMAGE_DIR}/ or {POLAR_DIR}/) at or under {root}")
    return sorted(found)


@dataclass(frozen=True)
class _SequenceMeta:
    """What windows need from one sequence, in compact arrays (picklable for DataLoader workers)."""

    name: str
    image_paths: list[Path]
    numbers: np.ndarray  # [N] int64 frame numbers
    timestamps: np.ndarray  # [N] float64
    poses: np.ndarray  # [N, 3]
    image_size: int
    boxes: list[np.ndarray]  # N x [M, 5] float64, all annotated objects (protocol applied per window)
    ids: list[np.ndarray]  # N x [M] int64
    classes: list[list[str]]  # N x M RADIATE class names


def _protocol(boxes: np.ndarray, ids: np.ndarray, classes: list[str], crop: int, resolution: float):
    """Keep objects not of a dropped class whose centre lies inside the crop -> (boxes, ids, classes)."""
    if len(boxes) == 0:
        return boxes.reshape(0, 5), ids.reshape(0), []
    uv = metres_to_pixels(boxes[:, :2], crop, resolution)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < crop) & (uv[:, 1] >= 0) & (uv[:, 1] < crop)
    keep = inside & np.array([c not in DROPPED_CLASSES for c in classes])
    return boxes[keep], ids[keep], [c for c, k in zip(classes, keep) if k]


class RadarWindowDataset(_Base):
    """Window k -> dict(frames uint8 [T, S, S], poses float64 [T, 3], boxes T x [M_t, 5], ids T x [M_t],
    classes T x [M_t] original names, sequence, frame (newest frame number), timestamps [T],
    augmentation {flip, angle})."""

    def __init__(
        self,
        root: str | Path,
        split: str | Sequence[str] | None = None,
        cfg: RaFDConfig | None = None,
        stride: int = 1,
        augment: bool | AugmentConfig = False,
        seed: int = 0,
    ) -> None:
        if cfg is None:
            raise ValueError("RadarWindowDataset needs cfg (input_size, num_frames, resolution)")
        if stride < 1:
            raise ValueError(f"stride must be >= 1, got {stride}")
        self.cfg, self.stride, self.seed = cfg, int(stride), int(seed)
        self.augment_config: AugmentConfig | None = (
            augment if isinstance(augment, AugmentConfig) else (AugmentConfig() if augment else None)
        )
        splits = None if split is None else ({split} if isinstance(split, str) else set(split))
        self.sequences: list[_SequenceMeta] = []
        seen_splits: dict[str | None, int] = {}
        for folder in find_sequences(root):
            sequence = read_sequence(folder)
            seen_splits[sequence.split] = seen_splits.get(sequence.split, 0) + 1
            if splits is not None and sequence.split not in splits:
                continue
            self.sequences.append(self._meta(sequence))
        if splits is not None and not self.sequences:
            log.warning("no sequence of split %s under %s (splits found: %s)", sorted(splits), root, seen_splits)
        self.windows: list[tuple[int, int]] = []  # (sequence index, first frame position)
        span = cfg.num_frames
        skipped = 0
        for s, meta in enumerate(self.sequences):
            for start in range(0, len(meta.numbers) - span + 1, self.stride):
                numbers = meta.numbers[start : start + span]
                if np.any(np.diff(numbers) != 1):
                    skipped += 1  # the window would jump over missing frame numbers
                    continue
                self.windows.append((s, start))
        if skipped:
            log.warning("skipped %d windows spanning gaps in the frame numbers", skipped)
        self._cache: OrderedDict[Path, np.ndarray] = OrderedDict()
        self._draws = 0
        log.info("%d windows of %d frames from %d sequences (split %s) under %s",
                 len(self.windows), span, len(self.sequences), split, root)

    def _meta(self, sequence) -> _SequenceMeta:
        if not sequence.annotated:
            raise FileNotFoundError(f"{sequence.path}: annotations/annotations.json not found (a training/evaluation dataset needs them)")
        if sequence.poses is None:  # read_sequence estimates them; None only if that was switched off
            raise ValueError(f"{sequence.path}: no ego poses")
        if abs(sequence.resolution - self.cfg.resolution) > 1e-6 * self.cfg.resolution:
            raise ValueError(f"{sequence.path}: resolution {sequence.resolution} m/px, the config expects {self.cfg.resolution}")
        if sequence.image_size < self.cfg.input_size or (sequence.image_size - self.cfg.input_size) % 2:
            raise ValueError(
                f"{sequence.path}: {sequence.image_size} px scans cannot be centre-cropped to {self.cfg.input_size} px "
                "around the radar (need a larger scan with an even difference)"
            )
        return _SequenceMeta(
            name=sequence.name,
            image_paths=[f.image_path for f in sequence.frames],
            numbers=np.array([f.number for f in sequence.frames], np.int64),
            timestamps=np.array([f.timestamp for f in sequence.frames], np.float64),
            poses=np.asarray(sequence.poses, np.float64),
            image_size=sequence.image_size,
            boxes=[np.array([o.box for o in f.objects], np.float64).reshape(-1, 5) for f in sequence.frames],
            ids=[np.array([o.id for o in f.objects], np.int64) for f in sequence.frames],
            classes=[[o.class_name for o in f.objects] for f in sequence.frames],
        )

    def __len__(self) -> int:
        return len(self.windows)

    def _image(self, path: Path) -> np.ndarray:
        image = self._cache.get(path)
        if image is None:
            image = load_image(path)
            self._cache[path] = image
            while len(self._cache) > IMAGE_CACHE_SIZE:
                self._cache.popitem(last=False)
        else:
            self._cache.move_to_end(path)
        return image

    def _draw(self, index: int) -> Augmentation:
        """A fresh augmentation: seeded by (seed, worker seed, index, draw count) -> reproducible per process,
        different across DataLoader workers and epochs (torch re-seeds workers every epoch)."""
        try:
            from torch.utils.data import get_worker_info

            info = get_worker_info()
        except ImportError:  # pragma: no cover
            info = None
        stream = int(info.seed) % (2**63) if info is not None else 0
        rng = np.random.default_rng([self.seed, stream, index, self._draws])
        self._draws += 1
        return Augmentation.sample(rng, self.augment_config)

    def __getitem__(self, index: int) -> dict[str, Any]:
        if not -len(self) <= index < len(self):
            raise IndexError(f"window {index} out of range ({len(self)} windows)")
        augmentation = self._draw(index % len(self)) if self.augment_config is not None else Augmentation()
        return self.window(index, augmentation)

    def window(self, index: int, augmentation: Augmentation = Augmentation()) -> dict[str, Any]:
        """Window `index` with a given augmentation (identity by default)."""
        s, start = self.windows[index]
        meta = self.sequences[s]
        span = range(start, start + self.cfg.num_frames)
        size, resolution = self.cfg.input_size, self.cfg.resolution
        frames = np.stack([augmentation.image(self._image(meta.image_paths[k]), size) for k in span])
        boxes, ids, classes = [], [], []
        for k in span:
            b, i, c = _protocol(augmentation.boxes(meta.boxes[k]), meta.ids[k], meta.classes[k], size, resolution)
            boxes.append(b)
            ids.append(i)
            classes.append(c)
        return {
            "frames": frames,  # uint8 [T, S, S]
            "poses": augmentation.poses(meta.poses[start : start + self.cfg.num_frames]),  # float64 [T, 3]
            "boxes": boxes,
            "ids": ids,
            "classes": classes,
            "sequence": meta.name,
            "frame": int(meta.numbers[start + self.cfg.num_frames - 1]),
            "timestamps": meta.timestamps[start : start + self.cfg.num_frames].copy(),
            "augmentation": {"flip": augmentation.flip, "angle": augmentation.angle},
        }
