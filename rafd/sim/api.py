"""Public entry points: simulate one RADIATE-format sequence or a whole split of them."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from rafd.geometry import RADIATE_SCAN_SIZE
from rafd.sim.sensor import Difficulty
from rafd.sim.sequence import run_simulation
from rafd.sim.writer import write_sequence


def sequence_seed(seed: int, index: int) -> int:
    """Independent per-sequence seed derived from (dataset seed, sequence index)."""
    return int(np.random.SeedSequence([int(seed), int(index)]).generate_state(1, np.uint64)[0])


def simulate_sequence(
    out_dir: str | Path,
    seed: int,
    num_frames: int,
    split: str = "train_good_weather",
    size: int = RADIATE_SCAN_SIZE,
    difficulty: Difficulty = Difficulty(),
    ambiguous: bool = True,
    poses: bool = True,
    polar: bool = False,
    weather: str | None = None,
) -> Path:
    """Simulate and write one sequence into the folder `out_dir` (its name becomes meta.json "name");
    `ambiguous` labels as RADIATE's annotators do (rafd.sim.sequence.ambiguous_labels); poses=False writes no
    ego_poses.csv (like a real RADIATE sequence before `rafd-odometry`); polar=True also writes the polar scans
    (Navtech_Polar/); `weather` forces the drive's weather (None: drawn per drive)."""
    out_dir = Path(out_dir)
    sequence = run_simulation(
        seed, num_frames, split, size, difficulty, name=out_dir.name, ambiguous=ambiguous, weather=weather
    )
    return write_sequence(sequence, out_dir, poses=poses, polar=polar)


def simulate_dataset(
    root: str | Path,
    sequences: int,
    frames: int,
    seed: int,
    split: str | Sequence[str] = "train_good_weather",
    size: int = RADIATE_SCAN_SIZE,
    difficulty: Difficulty = Difficulty(),
    ambiguous: bool = True,
    poses: bool = True,
    polar: bool = False,
    weather: str | None = None,
    progress: bool = True,
) -> list[Path]:
    """Write `sequences` folders root/sim_<seed>_<k>, each simulated from sequence_seed(seed, k); with several
    splits, sequence k goes to split k mod len(split). A progress bar over the sequences (rafd.progress)."""
    from rafd.progress import track

    if sequences < 1:
        raise ValueError(f"sequences must be >= 1, got {sequences}")
    splits = (split,) if isinstance(split, str) else tuple(split)
    if not splits:
        raise ValueError("at least one split")
    root = Path(root)
    return [
        simulate_sequence(
            root / f"sim_{seed}_{k}",
            sequence_seed(seed, k),
            frames,
            splits[k % len(splits)],
            size,
            difficulty,
            ambiguous,
            poses,
            polar,
            weather,
        )
        for k in track(range(sequences), desc=f"simulate {sequences} x {frames} frames", unit="seq", enabled=progress)
    ]
