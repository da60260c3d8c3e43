"""Opening window datasets for training/evaluation with clear errors (wraps rafd.data.RadarWindowDataset)."""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from torch.utils.data import Dataset, Subset

from rafd.config import RaFDConfig

log = logging.getLogger(__name__)


class DatasetError(ValueError):
    """A data root or split that cannot be used; the message names the path and split."""


def open_windows(
    root: str | Path, split: str | None, cfg: RaFDConfig, max_windows: int | None = None, augment: bool = False
) -> Dataset:
    """Windows of cfg.num_frames frames at cfg.input_size from the sequences of `split` under `root`."""
    from rafd.data import RadarWindowDataset

    root = Path(root)
    if not root.exists():
        raise DatasetError(f"data root {root} does not exist")
    if not root.is_dir():
        raise DatasetError(f"data root {root} is not a directory")
    try:
        dataset = RadarWindowDataset(root, split=split, cfg=cfg, augment=augment)
    except (FileNotFoundError, ValueError) as error:
        raise DatasetError(f"cannot open split {split!r} under {root}: {error}") from error
    if len(dataset) == 0:
        raise DatasetError(f"split {split!r} under {root} holds no windows of {cfg.num_frames} frames")
    if max_windows is not None and max_windows < len(dataset):
        # Evenly spaced, not the first N: keeps every sequence represented in a capped run.
        indices = np.linspace(0, len(dataset) - 1, max_windows).round().astype(int)
        log.info("using %d of %d windows", max_windows, len(dataset))
        return Subset(dataset, sorted(set(indices.tolist())))
    return dataset
