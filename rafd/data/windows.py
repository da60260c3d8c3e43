"""Opening window datasets for training/evaluation with clear errors (wraps rafd.data.RadarWindowDataset)."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np
from torch.utils.data import Dataset

from rafd.config import RaFDConfig

if TYPE_CHECKING:  # the data code loads lazily
    from rafd.data import RadarWindowDataset

log = logging.getLogger(__name__)


class DatasetError(ValueError):
    """A data root or split that cannot be used; the message names the path, the split and the fix."""


class WindowSubset(Dataset):
    """The windows `indices` of a window dataset; passes (epoch, index) keys through (torch's Subset does not)."""

    def __init__(self, dataset: Dataset, indices: Sequence[int]) -> None:
        self.dataset = dataset
        self.indices = list(indices)

    def __len__(self) -> int:
        return len(self.indices)

    @property
    def sequences(self) -> list:
        """The underlying dataset's sequences (names, conditions), which a subset of its windows still draws on."""
        # a window dataset: what open_windows and the trainer wrap
        return cast("RadarWindowDataset | WindowSubset", self.dataset).sequences

    def __getitem__(self, key: int | tuple[int, int]) -> Any:
        if isinstance(key, tuple):
            epoch, index = key
            return self.dataset[(epoch, self.indices[index])]
        return self.dataset[self.indices[key]]


def open_windows(
    root: str | Path,
    split: str | Sequence[str] | None,
    cfg: RaFDConfig,
    max_windows: int | None = None,
    augment=False,
    cache: str | Path | None = None,
    estimate_poses: bool = False,
    seed: int = 0,
    history: int | None = None,
    warm_up: bool = False,
) -> RadarWindowDataset | WindowSubset:
    """Windows of cfg.num_frames frames at cfg.input_size from the sequences of `split` (one name, a comma-separated
    list or a list) under `root`, scans from a prepared `cache` when given. `history` N keeps only the windows whose
    newest frame an N-frame model also scores (a model of fewer frames is then compared on equal frames). `warm_up`:
    also each sequence's first frames, in windows padded as the service pads a stream's first frames."""
    from rafd.data import RadarWindowDataset
    from rafd.data.cache import CacheError
    from rafd.data.dataset import MissingPosesError

    root = Path(root)
    if not root.exists():
        raise DatasetError(f"data root {root} does not exist")
    if not root.is_dir():
        raise DatasetError(f"data root {root} is not a directory")
    try:
        dataset = RadarWindowDataset(
            root,
            split=split,
            cfg=cfg,
            augment=augment,
            cache=cache,
            estimate_poses=estimate_poses,
            seed=seed,
            warm_up=warm_up,
        )
    except (MissingPosesError, CacheError) as error:
        raise DatasetError(str(error)) from error
    except (FileNotFoundError, ValueError) as error:
        raise DatasetError(f"cannot open split {split!r} under {root}: {error}") from error
    if len(dataset) == 0:
        raise DatasetError(f"split {split!r} under {root} holds no windows of {cfg.num_frames} frames")
    if history is not None and history > cfg.num_frames:
        before = len(dataset)
        if dataset.keep_newest_with_history(history) == 0:
            raise DatasetError(f"split {split!r} under {root} holds no frame with {history - 1} predecessors")
        log.info("scoring the %d of %d frames that a %d-frame model scores", len(dataset), before, history)
    if max_windows is not None and max_windows < len(dataset):
        # Evenly spaced, not the first N: keeps every sequence represented in a capped run.
        indices = np.linspace(0, len(dataset) - 1, max_windows).round().astype(int)
        log.info("using %d of %d windows", max_windows, len(dataset))
        return WindowSubset(dataset, sorted(set(indices.tolist())))
    return dataset
