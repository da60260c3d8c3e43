"""Windows of T consecutive radar frames under the benchmark protocol (a torch Dataset).

Protocol (TempoRadar / SIRA / RaFD on RADIATE): centre crop to cfg.input_size around the radar, objects
whose centre falls outside the crop dropped, pedestrian and group_of_pedestrians dropped, every other
class merged into `vehicle` (the window keeps the original class names in "classes").

Sequences: every folder holding Navtech_Cartesian/ under `root` (or `root` itself) whose meta.json "set" is one of
`split` (a name or a list of names; None = all). meta.json is read first: sequences of other splits are never read
further. Each selected sequence's metadata (frames, timestamps, boxes, ids, poses) is read once at construction.

Ego poses come from each sequence's ego_poses.csv, prepared once by `rafd-odometry ROOT`; a sequence without one is
an error naming that command, unless estimate_poses=True asks for radar odometry here (slow: ~150 ms per frame).

Scans: from a prepared cache (`rafd prepare ROOT --out CACHE`, rafd.data.cache: centre crops in one memory-mapped array
per sequence, no PNG decode per window) when `cache` is given, else decoded from the PNGs per window (slow).

Augmentation (augment=True or an enabled AugmentConfig): one rafd.data.augment.Augmentation per window, applied to the
scans before the crop and to boxes and poses; the crop protocol is applied to the augmented boxes. It is drawn from a
generator seeded by (seed, epoch, window index): ask for dataset[(epoch, index)] (rafd.train.distributed's
EpochSampler yields those keys) and the result depends on nothing else -- not on DataLoader workers, their number,
or where a run was resumed. dataset[index] draws as epoch 0.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, overload

import numpy as np

from rafd.config import RaFDConfig
from rafd.data.augment import Augmentation, AugmentConfig
from rafd.data.cache import CROPS_FILE, cache_folder, read_cached, required_crop
from rafd.data.folders import IMAGE_DIR, META_FILE, POLAR_DIR
from rafd.data.labels import IGNORE_CLASS
from rafd.data.native_folder import NATIVE_DIR, is_native_folder
from rafd.data.poses import POSES_FILE
from rafd.data.radiate_files import read_meta
from rafd.data.reader import read_sequence
from rafd.geometry import metres_to_pixels

try:  # a torch Dataset when torch is installed (DataLoader works with any __getitem__/__len__ object)
    from torch.utils.data import Dataset as _Base
except ImportError:  # pragma: no cover - torch-free installs
    _Base = object  # type: ignore[assignment,misc]

log = logging.getLogger(__name__)

DROPPED_CLASSES = frozenset({"pedestrian", "group_of_pedestrians", IGNORE_CLASS})


class MissingPosesError(ValueError):
    """Selected sequences have no ego_poses.csv and odometry was not asked for."""


@overload
def split_names(split: None) -> None: ...
@overload
def split_names(split: str | Sequence[str]) -> frozenset[str]: ...
def split_names(split: str | Sequence[str] | None) -> frozenset[str] | None:
    """'a', 'a,b' or ['a', 'b'] -> {'a', 'b'}; None -> None (every split)."""
    if split is None:
        return None
    parts = split.split(",") if isinstance(split, str) else [n for part in split for n in str(part).split(",")]
    names = frozenset(n.strip() for n in parts if n.strip())
    if not names:
        raise ValueError("no split name given")
    return names


def select_sequences(root: str | Path, split: str | Sequence[str] | None) -> tuple[list[Path], dict[str | None, int]]:
    """Sequence folders under `root` whose meta.json "set" is in `split` (only meta.json is read) ->
    (folders, {split: count} of everything found). A ROS 2 bag named as `root` is the one sequence, whatever the
    split (a bag has none)."""
    from rafd.ros.sequence import is_bag

    if is_bag(root):
        return [Path(root)], {None: 1}
    wanted = split_names(split)
    chosen: list[Path] = []
    seen: dict[str | None, int] = {}
    for folder in find_sequences(root):
        name = read_meta(folder / META_FILE).get("set")
        seen[name] = seen.get(name, 0) + 1
        if wanted is None or name in wanted:
            chosen.append(folder)
    return chosen, seen


def find_sequences(root: str | Path) -> list[Path]:
    """Sequence folders (holding Navtech_Cartesian/, or only the polar scans Navtech_Polar/, or native scans in
    radar/) at or under `root`, sorted, or `root` itself when it is a ROS 2 bag; FileNotFoundError if none."""
    from rafd.ros.sequence import is_bag

    root = Path(root)
    if is_bag(root):
        return [root]
    if not root.is_dir():
        raise FileNotFoundError(f"data root {root} not found or not a directory")
    scan_dirs = {IMAGE_DIR, POLAR_DIR}
    if any((root / name).is_dir() for name in scan_dirs) or is_native_folder(root):
        return [root]
    found = []
    for current, folders, _ in os.walk(root):
        if scan_dirs & set(folders) or (NATIVE_DIR in folders and is_native_folder(Path(current))):
            found.append(Path(current))
            folders[:] = []  # a sequence folder holds no further sequences
        else:
            folders.sort()
    if not found:
        raise FileNotFoundError(
            f"no sequence folders (with {IMAGE_DIR}/, {POLAR_DIR}/ or native {NATIVE_DIR}/) at or under {root}"
        )
    return sorted(found)


@dataclass(frozen=True)
class _SequenceMeta:
    """What windows need from one sequence, in compact arrays (picklable for DataLoader workers)."""

    name: str
    frames: list  # N rafd.data.frames.RadarFrame (load() decodes a Cartesian scan or converts a polar one)
    numbers: np.ndarray  # [N] int64 frame numbers
    timestamps: np.ndarray  # [N] float64
    poses: np.ndarray  # [N, 3]
    image_size: int
    boxes: list[np.ndarray]  # N x [M, 5] float64, all annotated objects (protocol applied per window)
    ids: list[np.ndarray]  # N x [M] int64
    classes: list[list[str]]  # N x M RADIATE class names
    cache: Path | None = None  # CACHE/<sequence> with crops.npy, when prepared
    condition: str | None = None  # meta.json's weather / RADIATE type (rafd.data.radiate_files.meta_condition)


def objects_in_crop(boxes: np.ndarray, ids: np.ndarray, classes: list[str], crop: int, resolution: float):
    """Keep objects not of a dropped class whose centre lies inside the crop -> (boxes, ids, classes, ignore boxes):
    the labeller's ignore regions (rafd.data.labels.IGNORE_CLASS) that touch the crop, kept apart."""
    if len(boxes) == 0:
        return boxes.reshape(0, 5), ids.reshape(0), [], np.zeros((0, 5))
    uv = metres_to_pixels(boxes[:, :2], crop, resolution)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < crop) & (uv[:, 1] >= 0) & (uv[:, 1] < crop)
    keep = inside & np.array([c not in DROPPED_CLASSES for c in classes])
    reach = np.hypot(boxes[:, 2], boxes[:, 3]) / 2.0 / resolution  # pixels from its centre a box may reach
    near = (uv[:, 0] > -reach) & (uv[:, 0] < crop + reach) & (uv[:, 1] > -reach) & (uv[:, 1] < crop + reach)
    ignore = near & np.array([c == IGNORE_CLASS for c in classes])
    return boxes[keep], ids[keep], [c for c, k in zip(classes, keep) if k], boxes[ignore]


class RadarWindowDataset(_Base):
    """Window k (or key (epoch, k)) -> dict(frames uint8 [T, S, S], poses float64 [T, 3], boxes T x [M_t, 5],
    ids T x [M_t], classes T x [M_t] original names, sequence, frame (newest frame number), timestamps [T],
    augmentation {flip, angle})."""

    def __init__(
        self,
        root: str | Path,
        split: str | Sequence[str] | None = None,
        cfg: RaFDConfig | None = None,
        stride: int = 1,
        augment: bool | AugmentConfig = False,
        seed: int = 0,
        cache: str | Path | None = None,
        estimate_poses: bool = False,
        warm_up: bool = False,
    ) -> None:
        """`warm_up`: also the windows of each sequence's first T-1 frames, their old end padded by repeating the
        oldest frame with its pose, as the service answers a stream's first frames (rafd.model.RaFD.step):
        every frame of a short sequence is scored (or trained on) by a T-frame model."""
        if cfg is None:
            raise ValueError("RadarWindowDataset needs cfg (input_size, num_frames, resolution)")
        if stride < 1:
            raise ValueError(f"stride must be >= 1, got {stride}")
        self.cfg, self.stride, self.seed = cfg, int(stride), int(seed)
        if not isinstance(augment, AugmentConfig):
            augment = AugmentConfig(enabled=bool(augment))
        self.augment_config: AugmentConfig | None = augment if augment.enabled else None
        self.cache_root = None if cache is None else Path(cache)
        folders, seen_splits = select_sequences(root, split)
        if split is not None and not folders:
            log.warning(
                "no sequence of split %s under %s (splits found: %s)", sorted(split_names(split)), root, seen_splits
            )
        sequences = [read_sequence(folder, estimate_poses=estimate_poses) for folder in folders]
        missing = [s.path for s in sequences if s.poses is None]
        if missing:
            names = ", ".join(str(p) for p in missing[:3]) + (" ..." if len(missing) > 3 else "")
            raise MissingPosesError(
                f"{len(missing)} of {len(sequences)} sequences have no {POSES_FILE} ({names}): prepare them once with "
                f"`rafd-odometry {root}` (radar odometry, in parallel, resumable), or ask for odometry now "
                "with `rafd eval --estimate-poses` or `rafd train ... data.estimate_poses=true` (slow)"
            )
        self.sequences: list[_SequenceMeta] = [self._meta(sequence, Path(root)) for sequence in sequences]
        self.windows: list[tuple[int, int]] = []  # (sequence index, first frame position)
        span = cfg.num_frames
        skipped = 0
        first = -(span - 1) if warm_up else 0
        for s, meta in enumerate(self.sequences):
            for start in range(first, len(meta.numbers) - span + 1, self.stride):
                numbers = meta.numbers[self.positions(start)]
                if np.any(np.diff(numbers) > 1):
                    skipped += 1  # the window would jump over missing frame numbers
                    continue
                self.windows.append((s, start))
        if skipped:
            log.warning("skipped %d windows spanning gaps in the frame numbers", skipped)
        self._crops: dict[int, np.ndarray] = {}  # sequence index -> memory-mapped crops (opened per process)
        log.info(
            "%d windows of %d frames from %d sequences (split %s) under %s%s",
            len(self.windows),
            span,
            len(self.sequences),
            split,
            root,
            "" if self.cache_root is None else f", scans from the cache {self.cache_root}",
        )

    def positions(self, start: int) -> np.ndarray:
        """Frame positions of the window starting at `start` (negative in a warm-up window: repeats the first)."""
        return np.maximum(np.arange(start, start + self.cfg.num_frames), 0)

    def keep_newest_with_history(self, frames: int) -> int:
        """Keep only the windows whose newest frame has `frames` - 1 consecutive predecessors in its sequence: the
        frames a `frames`-frame model scores, so a model of fewer frames is compared on equal frames.
        -> windows kept."""
        kept = []
        for s, start in self.windows:
            newest = start + self.cfg.num_frames - 1
            first = newest - (frames - 1)
            if first >= 0 and np.all(np.diff(self.sequences[s].numbers[first : newest + 1]) == 1):
                kept.append((s, start))
        self.windows = kept
        return len(kept)

    def _meta(self, sequence, root: Path) -> _SequenceMeta:
        if not sequence.annotated:
            raise FileNotFoundError(
                f"{sequence.path}: annotations/annotations.json not found (a training/evaluation dataset needs them)"
            )
        if abs(sequence.resolution - self.cfg.resolution) > 1e-6 * self.cfg.resolution:
            raise ValueError(
                f"{sequence.path}: resolution {sequence.resolution} m/px, the config expects {self.cfg.resolution}"
            )
        if sequence.image_size < self.cfg.input_size or (sequence.image_size - self.cfg.input_size) % 2:
            raise ValueError(
                f"{sequence.path}: {sequence.image_size} px scans cannot be centre-cropped to {self.cfg.input_size} px "
                "around the radar (need a larger scan with an even difference)"
            )
        numbers = np.array([f.number for f in sequence.frames], np.int64)
        cache = None
        if self.cache_root is not None:
            augment = self.augment_config
            rotates = augment is not None and augment.max_rotation_deg > 0
            shift = 0.0 if augment is None or augment.shift_probability == 0 else augment.shift_max_m
            needed = min(required_crop(self.cfg.input_size, rotates, shift, self.cfg.resolution), sequence.image_size)
            cache = read_cached(
                cache_folder(self.cache_root, root, sequence.path), numbers, sequence.image_size, needed
            ).folder
        return _SequenceMeta(
            name=sequence.name,
            frames=[dataclasses.replace(f, objects=[]) for f in sequence.frames],  # objects live in boxes/ids below
            numbers=numbers,
            timestamps=np.array([f.timestamp for f in sequence.frames], np.float64),
            poses=np.asarray(sequence.poses, np.float64),
            image_size=sequence.image_size,
            boxes=[np.array([o.box for o in f.objects], np.float64).reshape(-1, 5) for f in sequence.frames],
            ids=[np.array([o.id for o in f.objects], np.int64) for f in sequence.frames],
            classes=[[o.class_name for o in f.objects] for f in sequence.frames],
            cache=cache,
            condition=sequence.condition,
        )

    def __len__(self) -> int:
        return len(self.windows)

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["_crops"] = {}  # memory maps are reopened in each worker process
        return state

    def _scan(self, sequence: int, position: int) -> np.ndarray:
        """uint8 [N, N] scan (or its prepared centre crop) of one frame, radar at the centre."""
        meta = self.sequences[sequence]
        if meta.cache is None:
            return meta.frames[position].load()
        crops = self._crops.get(sequence)
        if crops is None:
            crops = self._crops[sequence] = np.load(meta.cache / CROPS_FILE, mmap_mode="r")
        return crops[position]

    def augmentation(self, index: int, epoch: int = 0) -> Augmentation:
        """The augmentation of window `index` in `epoch`: a function of (seed, epoch, index) only."""
        if self.augment_config is None:
            return Augmentation()
        rng = np.random.default_rng([self.seed, int(epoch), int(index)])
        return Augmentation.sample(rng, self.augment_config, self.cfg.resolution)

    def __getitem__(self, key: int | tuple[int, int]) -> dict[str, Any]:
        epoch, index = key if isinstance(key, tuple) else (0, key)
        if not -len(self) <= index < len(self):
            raise IndexError(f"window {index} out of range ({len(self)} windows)")
        index %= len(self)
        return self.window(index, self.augmentation(index, epoch))

    def window(self, index: int, augmentation: Augmentation = Augmentation()) -> dict[str, Any]:
        """Window `index` with a given augmentation (identity by default)."""
        s, start = self.windows[index]
        meta = self.sequences[s]
        span = self.positions(start)
        size, resolution = self.cfg.input_size, self.cfg.resolution
        frames = augmentation.intensity(np.stack([augmentation.image(self._scan(s, k), size) for k in span]))
        boxes, ids, classes, ignore = [], [], [], []
        for k in span:
            b, i, c, g = objects_in_crop(
                augmentation.boxes(meta.boxes[k]), meta.ids[k], meta.classes[k], size, resolution
            )
            boxes.append(b)
            ids.append(i)
            classes.append(c)
            ignore.append(g)
        return {
            "frames": frames,  # uint8 [T, S, S]
            "poses": augmentation.poses(meta.poses[span]),  # float64 [T, 3]
            "boxes": boxes,
            "ids": ids,
            "classes": classes,
            "ignore": ignore,  # T x [K, 5] regions the labeller left undecided: neither rewarded nor penalised
            "sequence": meta.name,
            "frame": int(meta.numbers[span[-1]]),
            "timestamps": meta.timestamps[span].copy(),
            "augmentation": augmentation.as_dict(),
        }
