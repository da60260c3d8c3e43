"""RADIATE data: sequence reader (numpy + opencv; the scan formats themselves are rafd.scans), ego pose files, and
the torch window dataset.

`read_sequence` and the pose file helpers are torch-free; `RadarWindowDataset` imports torch on first
access (so `rafd.data` stays importable where only the reader is needed, e.g. rafd-client).
"""

from __future__ import annotations

from typing import Any

from rafd.data.frames import RadarFrame, RadarObject, RadarSequence
from rafd.data.poses import POSES_FILE, read_ego_poses, write_ego_poses
from rafd.data.reader import read_sequence
from rafd.scans.cartesian import load_image

__all__ = [
    "POSES_FILE",
    "RadarFrame",
    "RadarObject",
    "RadarSequence",
    "RadarWindowDataset",
    "find_sequences",
    "load_image",
    "read_ego_poses",
    "read_sequence",
    "write_ego_poses",
]


def __getattr__(name: str) -> Any:
    if name in ("RadarWindowDataset", "find_sequences"):
        from rafd.data import dataset

        return getattr(dataset, name)
    raise AttributeError(f"module 'rafd.data' has no attribute {name!r}")
