"""Decoding every scan of a data root once into memory-mapped centre crops (rafd.data.cache), resumable: a sequence
whose cache is complete and matches its frames is skipped."""

from __future__ import annotations

import functools
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rafd.cpu import usable_cpus
from rafd.data.cache import DEFAULT_CROP, CacheError, cache_folder, read_cached, write_cached
from rafd.data.dataset import select_sequences
from rafd.data.parallel import run_per_sequence
from rafd.data.reader import read_sequence


def prepare_sequence(folder: Path, root: Path, cache_root: Path, crop: int, force: bool) -> tuple[str, int, float]:
    """Cache one sequence -> (status "prepared" | "skipped", frames, seconds)."""
    start = time.perf_counter()
    sequence = read_sequence(folder, estimate_poses=False)
    target = cache_folder(cache_root, root, folder)
    numbers = np.array([f.number for f in sequence.frames], np.int64)
    if not force:
        try:
            read_cached(target, numbers, sequence.image_size, min(crop, sequence.image_size))
            return "skipped", len(numbers), time.perf_counter() - start
        except CacheError:
            pass  # absent, incomplete or stale: (re)build it
    write_cached(
        target, (frame.load() for frame in sequence.frames), numbers.tolist(), crop, sequence.image_size, folder
    )
    return "prepared", len(numbers), time.perf_counter() - start


@dataclass
class Prepared:
    """What prepare_root did: sequences prepared and skipped, frames decoded, seconds, failures ("folder: error")."""

    prepared: int = 0
    skipped: int = 0
    frames: int = 0
    seconds: float = 0.0
    failures: list[str] = field(default_factory=list)


def prepare_root(
    root: Path,
    cache: Path,
    splits: Sequence[str] | None = None,
    crop: int = DEFAULT_CROP,
    workers: int | None = None,
    force: bool = False,
    progress: bool = True,
) -> Prepared:
    """Cache every sequence of `splits` (all when None) under `root` into `cache`, in `workers` processes.
    ValueError for a bad crop or worker count, or when no sequence is selected; FileNotFoundError for a bad root."""
    workers = usable_cpus() if workers is None else workers
    if crop < 16 or crop % 2:
        raise ValueError(f"--crop-size must be an even number of pixels >= 16, got {crop}")
    if workers < 1:
        raise ValueError("--workers must be >= 1")
    folders, seen = select_sequences(root, list(splits) if splits else None)
    if not folders:
        raise ValueError(f"no sequence of split {splits} under {root} (splits: {seen})")
    cache.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    job = functools.partial(prepare_sequence, root=root, cache_root=cache, crop=crop, force=force)
    results, failures = run_per_sequence(job, folders, workers, "prepare", progress=progress)
    done = Prepared(failures=failures)
    for _, (status, count, _) in results:
        if status == "prepared":
            done.prepared += 1
            done.frames += count
        else:
            done.skipped += 1
    done.seconds = time.perf_counter() - start
    return done
