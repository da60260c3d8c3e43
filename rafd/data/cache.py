"""Prepared scan cache: each sequence's scans decoded once into one memory-mapped uint8 array of centre crops.

A RADIATE scan is a 1152 x 1152 PNG (~25 ms to decode) of which training keeps a 256 px centre crop; decoding four
full scans per window starves a GPU. `rafd prepare ROOT --out CACHE` decodes every scan once and keeps the centre
`crop` pixels (rafd.preprocess.model_crop) -- large enough for the window augmentation's rotations
(required_crop) -- in CACHE/<sequence path under ROOT>/crops.npy, [N, crop, crop] uint8, opened with mmap.
CACHE/<sequence>/cache.json is written last and marks the sequence complete (so `rafd-prepare` is resumable);
it records the frame numbers, the crop, the source folder and the scan size, which the dataset checks.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rafd.preprocess import model_crop, rotation_crop

CACHE_FILE = "cache.json"
CROPS_FILE = "crops.npy"
CACHE_VERSION = 1
DEFAULT_CROP = 384  # covers a 256 px input turned by any angle (needs 364)


def required_crop(input_size: int, rotates: bool, shift_m: float = 0.0, resolution: float = 1.0) -> int:
    """Smallest even crop from which rafd.data.augment can cut an input_size crop (turned by any angle when `rotates`,
    centred up to shift_m metres from the radar)."""
    side = rotation_crop(input_size) if rotates else input_size
    return side + 2 * math.ceil(shift_m / resolution) + 2 if shift_m > 0 else side


class CacheError(ValueError):
    """A cache that is missing, incomplete or does not match its source sequence; the message names the fix."""


@dataclass(frozen=True)
class CachedSequence:
    folder: Path  # CACHE/<sequence>
    numbers: np.ndarray  # [N] frame numbers, in the sequence's order
    crop: int
    image_size: int  # side of the source scans

    def open(self) -> np.ndarray:
        """[N, crop, crop] uint8, memory-mapped read-only (cheap to open in every DataLoader worker)."""
        return np.load(self.folder / CROPS_FILE, mmap_mode="r")


def cache_folder(cache_root: str | os.PathLike[str], data_root: str | os.PathLike[str], sequence: Path) -> Path:
    """CACHE/<sequence path relative to the data root> (the root itself when it is the sequence)."""
    relative = Path(sequence).resolve().relative_to(Path(data_root).resolve())
    return Path(cache_root) / relative


def read_cached(folder: Path, numbers: np.ndarray, image_size: int, min_crop: int) -> CachedSequence:
    """The cache of one sequence, checked against the sequence's frames; CacheError naming the fix otherwise."""
    marker = folder / CACHE_FILE
    if not marker.is_file():
        raise CacheError(f"{folder}: not prepared (no {CACHE_FILE}); run `rafd prepare DATA_ROOT --out CACHE_ROOT`")
    try:
        info = json.loads(marker.read_text())
        cached = CachedSequence(
            folder, np.asarray(info["numbers"], np.int64), int(info["crop"]), int(info["image_size"])
        )
        version = info["version"]
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise CacheError(f"{marker}: unreadable cache record ({error}); rerun `rafd prepare ... --force`") from error
    if version != CACHE_VERSION:
        raise CacheError(f"{marker}: cache version {version}, this rafd reads {CACHE_VERSION}; rerun rafd prepare")
    if not np.array_equal(cached.numbers, numbers) or cached.image_size != image_size:
        raise CacheError(
            f"{folder}: prepared from other frames than the sequence now holds; rerun `rafd prepare ... --force`"
        )
    if cached.crop < min_crop:
        raise CacheError(
            f"{folder}: crops of {cached.crop} px, this run needs {min_crop} px "
            f"(rerun `rafd prepare ... --crop-size {min_crop} --force`)"
        )
    return cached


def write_cached(folder: Path, scans, numbers: list[int], crop: int, image_size: int, source: Path) -> Path:
    """Decode-and-crop every scan (an iterable of uint8 [S, S]) into folder/crops.npy, then write cache.json."""
    folder.mkdir(parents=True, exist_ok=True)
    crop = min(crop, image_size)
    temporary = folder / f".{CROPS_FILE}.{os.getpid()}.tmp"
    array = np.lib.format.open_memmap(temporary, mode="w+", dtype=np.uint8, shape=(len(numbers), crop, crop))
    try:
        count = 0
        for index, scan in enumerate(scans):
            array[index] = model_crop(scan, crop)
            count += 1
        if count != len(numbers):
            raise ValueError(f"{source}: {count} scans for {len(numbers)} frames")
        array.flush()
        del array
        os.replace(temporary, folder / CROPS_FILE)
    finally:
        temporary.unlink(missing_ok=True)
    record = {
        "version": CACHE_VERSION,
        "numbers": [int(n) for n in numbers],
        "crop": crop,
        "image_size": int(image_size),
        "source": str(Path(source).resolve()),
    }
    marker_tmp = folder / f".{CACHE_FILE}.tmp"
    marker_tmp.write_text(json.dumps(record))
    os.replace(marker_tmp, folder / CACHE_FILE)  # last: marks the sequence complete
    return folder
