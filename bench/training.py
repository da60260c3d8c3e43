"""The training-speed benchmark (`rafd bench training`): what training at RADIATE scale costs, measured side by
side in one run.

loader: a RADIATE-scale simulated root in RADIATE's format (1152 px scans, no pose files) through `rafd odometry`
and `rafd prepare`, then windows per second per worker process (dataset + augmentation + targets + collate, the
work one DataLoader worker does) from the cache and from the PNGs, and a DataLoader with several workers over the
cache.

precision: training step time (forward, loss, backward, optimizer) in fp32 and bf16 autocast, interleaved, for the
tiny config at 256 px and the paper config at batch 1; then the loss curves of a short fp32 and bf16 run from the
same seed and data, every 10 steps side by side.
"""

from __future__ import annotations

import json
import logging
import statistics
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from rafd.progress import is_quiet, stage

if TYPE_CHECKING:  # torch loads lazily
    from torch.utils.data import Dataset

log = logging.getLogger("rafd.train_bench")


def _median_ms(samples: list[float]) -> float:
    return 1e3 * statistics.median(samples)


# ---------------------------------------------------------------- loader
def windows_per_second(dataset, keys: list, collate: Callable) -> float:
    """Windows per second of one process doing a DataLoader worker's job (getitem + collate) on `keys`."""
    start = time.perf_counter()
    for key in keys:
        collate([dataset[key]])
    return len(keys) / (time.perf_counter() - start)


def dataloader_windows_per_second(dataset, collate: Callable, workers: int, windows: int, batch: int = 8) -> float:
    """Windows per second through a torch DataLoader with `workers` processes (after a warm-up batch per worker)."""
    from torch.utils.data import DataLoader

    from rafd.train.distributed import DistContext, make_sampler

    sampler = make_sampler(dataset, DistContext(), seed=0)
    loader = DataLoader(
        dataset,
        batch_size=batch,
        sampler=sampler,
        num_workers=workers,
        collate_fn=collate,
        persistent_workers=workers > 0,
        prefetch_factor=4 if workers else None,
    )
    iterator = iter(loader)
    for _ in range(max(1, workers)):
        next(iterator)
    start, seen = time.perf_counter(), 0
    while seen < windows:
        try:
            seen += len(next(iterator))
        except StopIteration:
            iterator = iter(loader)
    return seen / (time.perf_counter() - start)


def run_loader(
    work: Path | None, sequences: int, frames: int, windows: int, workers: Sequence[int], prepare_workers: int
) -> int:
    """Time odometry, cache preparation and window loading on a simulated RADIATE-scale root; print the rows."""
    import torch

    from rafd.config import RaFDConfig
    from rafd.data import RadarWindowDataset
    from rafd.data.collate import Collator
    from rafd.data.dataset import select_sequences
    from rafd.data.ego_motion import write_poses
    from rafd.data.prepare import prepare_root
    from rafd.sim import simulate_dataset

    work = Path(work or tempfile.mkdtemp(prefix="rafd-loader-"))
    root, cache = work / "root", work / "cache"
    rows: list[tuple[str, str]] = []
    start = time.perf_counter()
    simulate_dataset(root, sequences, frames, seed=31, split="train_good_weather", size=1152, poses=False)
    total = sequences * frames
    rows.append(("simulate (not part of training)", f"{total / (time.perf_counter() - start):.1f} frames/s"))
    start = time.perf_counter()
    _, failures = write_poses(select_sequences(root, None)[0], prepare_workers)  # its own progress bar
    if failures:
        raise RuntimeError(f"odometry failed: {failures[0]}")
    rows.append(
        (f"rafd odometry ROOT ({prepare_workers} processes)", f"{total / (time.perf_counter() - start):.1f} frames/s")
    )
    start = time.perf_counter()
    prepared = prepare_root(root, cache, workers=prepare_workers)
    if prepared.failures:
        raise RuntimeError(f"preparing the cache failed: {prepared.failures[0]}")
    rows.append(
        (
            f"rafd prepare ROOT --out CACHE ({prepare_workers} processes)",
            f"{total / (time.perf_counter() - start):.1f} frames/s",
        )
    )

    torch.set_num_threads(1)  # as in a DataLoader worker process
    cfg = RaFDConfig.paper()  # the protocol's 256 px crop, 4 frames
    collate = Collator(cfg)
    rng = np.random.default_rng(0)
    for source, cache_root, count in (("cache", cache, windows), ("PNG", None, max(8, windows // 10))):
        for augment in (False, True):
            stage(f"time {count} windows, 1 worker, {source}, {'flip + rotation' if augment else 'no augmentation'}")
            dataset = RadarWindowDataset(root, cfg=cfg, augment=augment, cache=cache_root)
            keys = [(0, int(i)) for i in rng.integers(0, len(dataset), count)]  # shuffled: no decode cache helps
            rate = windows_per_second(dataset, keys, collate)
            rows.append(
                (
                    f"1 worker, {source}, {'flip + rotation' if augment else 'no augmentation'}",
                    f"{rate:.1f} windows/s per worker ({1e3 / rate:.1f} ms/window)",
                )
            )
    dataset = RadarWindowDataset(root, cfg=cfg, augment=True, cache=cache)
    for count in workers:
        stage(f"time {windows} windows through a DataLoader with {count} workers")
        rate = dataloader_windows_per_second(dataset, collate, count, windows)
        rows.append(
            (
                f"DataLoader, {count} workers, cache, flip + rotation",
                f"{rate:.1f} windows/s ({rate / max(count, 1):.1f} per worker)",
            )
        )
    print(
        f"\nloader benchmark: {sequences} sequences x {frames} frames of 1152 px, 256 px windows of 4 "
        f"frames, targets and collate included ({work})"
    )
    width = max(len(name) for name, _ in rows)
    for name, value in rows:
        print(f"  {name:<{width}}  {value}")
    return 0


# ---------------------------------------------------------------- precision
def _training_batch(cfg, batch_size: int):
    """A batch of real simulated windows (objects, flow targets) at cfg's size."""
    from rafd.data import RadarWindowDataset
    from rafd.data.collate import Collator
    from rafd.sim import simulate_dataset

    with tempfile.TemporaryDirectory() as folder:
        simulate_dataset(folder, 1, cfg.num_frames + batch_size, seed=3, split="train", size=cfg.input_size + 64)
        dataset = RadarWindowDataset(folder, cfg=cfg)
        return Collator(cfg)([dataset[i] for i in range(batch_size)])


def step_times(cfg, batch_size: int, steps: int) -> dict[str, float]:
    """Median ms per optimizer step in fp32 and bf16 (interleaved, so machine noise hits both alike)."""
    from rafd.train.config import RunConfig, TrainConfig
    from rafd.train.distributed import DistContext
    from rafd.train.trainer import Trainer

    stage(f"time {steps} training steps of {cfg.input_size} px, batch {batch_size}, in fp32 and bf16")
    batch = _training_batch(cfg, batch_size)
    trainers = {
        precision: Trainer(
            RunConfig(
                model=cfg,
                train=TrainConfig(
                    batch_size=batch_size, precision=precision, progress=False, device="cpu", optimizer="adam"
                ),
            ),
            cast("Dataset[Any]", [0]),  # a stand-in: train_step gets its batch from here
            None,
            DistContext(),
        )
        for precision in ("fp32", "bf16")
    }
    samples: dict[str, list[float]] = {p: [] for p in trainers}
    for step in range(steps + 1):
        for precision, trainer in trainers.items():
            start = time.perf_counter()
            trainer.train_step(batch).tolist()  # .tolist(): wait for the step to finish
            if step:  # the first step allocates and warms up
                samples[precision].append(time.perf_counter() - start)
    return {p: _median_ms(s) for p, s in samples.items()}


def loss_curves(steps: int, log_every: int) -> dict[str, list[dict]]:
    """The tiny recipe on a small simulated root for `steps` steps in fp32 and bf16 from one seed -> curves."""
    from rafd.config import RaFDConfig
    from rafd.data.windows import open_windows
    from rafd.sim import simulate_dataset
    from rafd.train.config import RunConfig, TrainConfig
    from rafd.train.distributed import DistContext
    from rafd.train.trainer import Trainer

    cfg = RaFDConfig.tiny()
    curves = {}
    with tempfile.TemporaryDirectory() as folder:
        simulate_dataset(folder, 4, 30, seed=12, split="train", size=256)
        dataset = open_windows(folder, "train", cfg, augment=True)
        for precision in ("fp32", "bf16"):
            stage(f"loss curve: {steps} steps in {precision}")
            train_cfg = TrainConfig(
                epochs=1,
                batch_size=4,
                lr=1e-3,
                optimizer="adamw",
                precision=precision,
                max_steps_per_epoch=steps,
                log_every=log_every,
                device="cpu",
                progress=not is_quiet(),
                val_every=0,
                seed=0,
            )
            history = Trainer(RunConfig(model=cfg, train=train_cfg), dataset, None, DistContext()).fit()
            curves[precision] = history[0]["curve"]
    return curves


def run_precision(steps: int, curve_steps: int, threads: int, json_path: Path | None) -> int:
    """Time fp32 against bf16 training steps and print a short run's two loss curves side by side."""
    import torch

    from rafd.config import RaFDConfig
    from rafd.model.precision import cpu_has_bf16

    torch.set_num_threads(threads)
    print(f"\nprecision benchmark: {threads} threads, CPU bf16 units: {cpu_has_bf16()}")
    for name, cfg, batch in (
        ("tiny, 256 px, batch 4", RaFDConfig.tiny(input_size=256), 4),
        ("paper, 256 px, batch 1", RaFDConfig.paper(), 1),
    ):
        times = step_times(cfg, batch, steps)
        print(
            f"  {name:<24} fp32 {times['fp32']:8.0f} ms/step   bf16 {times['bf16']:8.0f} ms/step   "
            f"bf16 speed-up {times['fp32'] / times['bf16']:.2f}x"
        )
    curves = loss_curves(curve_steps, 10)
    print("\nloss curves, tiny recipe (128 px, batch 4, AdamW 1e-3), mean of every 10 steps, seed 0:")
    print(f"  {'step':>5} {'fp32 total':>11} {'bf16 total':>11} {'rel. diff':>9}")
    differences = []
    for a, b in zip(curves["fp32"], curves["bf16"]):
        difference = abs(b["loss_total"] - a["loss_total"]) / abs(a["loss_total"])
        differences.append(difference)
        print(f"  {a['step']:>5} {a['loss_total']:>11.4f} {b['loss_total']:>11.4f} {100 * difference:>8.1f}%")
    first, last = curves["fp32"][0]["loss_total"], curves["fp32"][-1]["loss_total"]
    print(f"  fp32 loss fell {first:.3f} -> {last:.3f}; largest bf16/fp32 difference {100 * max(differences):.1f}%")
    if json_path:
        Path(json_path).write_text(json.dumps(curves, indent=2))
    return 0
