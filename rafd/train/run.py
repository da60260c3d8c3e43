"""One training run as plain Python: `train(TrainRun(config, data, out))`. The run config (rafd.train.config: network,
data and augmentation, loss, training) says what is trained and how; the run says where: the data root with its
splits and scan cache, the checkpoint to write, where the weights start, and the validation and mixed-in roots.
`rafd train` builds one from its command line (rafd.cli.train), the synthetic benchmark's variants theirs directly
(bench.variants).
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rafd.cpu import usable_cpus
from rafd.train.config import RunConfig

if TYPE_CHECKING:  # torch is imported when a run starts, not when it is described
    from torch.utils.data import Dataset

    from rafd.train.distill import Teacher
    from rafd.train.distributed import DistContext

log = logging.getLogger("rafd.train")


@dataclass(frozen=True)
class DataSource:
    """A data root holding sequence folders, the splits read from it (meta.json 'set' names) and, when prepared, its
    scan cache (rafd prepare)."""

    root: Path
    splits: tuple[str, ...]
    cache: Path | None = None


@dataclass(frozen=True)
class TrainRun:
    config: RunConfig  # what is trained and how
    data: DataSource  # the training windows
    out: Path  # the checkpoint written (+ .optim.pt, .history.json beside it)
    recipe: str = "custom"  # the recipe the config started from, recorded in the checkpoint
    resume: bool = False  # continue the unfinished run in `out` (the config must be the run's)
    # start from this checkpoint's weights where names and shapes match (e.g. a single-frame model under a 4-frame
    # run); optimizer, schedule and epochs start fresh
    init: Path | None = None
    val: DataSource | None = None  # validation windows, scored every train.val_every epochs
    # every epoch holds each of `data`'s windows once plus `mix`'s up to data.mix_share of the epoch (in turn over
    # the epochs, augmented as data.mix_augment says)
    mix: DataSource | None = None
    # a trained model whose heatmap the run learns beside the labels (loss.distill_weight; rafd.train.distill)
    teacher: Path | None = None


def default_threads(world_size: int) -> int:
    """CPUs this process may use (rafd.cpu.usable_cpus) shared among the local processes."""
    return max(1, usable_cpus() // max(1, world_size))


class TrainSetupError(Exception):
    """The run cannot start: its data, the config, the starting checkpoint or the process group; the message says
    what and how to fix it. Raised before any training step."""


@dataclass(frozen=True)
class _Prepared:
    run: TrainRun
    train_set: Dataset[Any]
    val_set: Dataset[Any] | None
    ctx: DistContext
    run_meta: dict[str, Any]
    teacher: Teacher | None


def train(run: TrainRun) -> list[dict[str, Any]]:
    """Train one model as `run` says (one process, or one rank under torchrun) -> the epochs' history.

    Raises TrainSetupError before any training starts when the run cannot start."""
    from rafd.data.windows import DatasetError

    try:
        prepared = _prepare(run)
    except (DatasetError, ValueError, RuntimeError) as error:
        raise TrainSetupError(str(error)) from error
    return _fit(prepared)


def _prepare(run: TrainRun) -> _Prepared:
    """Everything checked and opened before the first step: the config, the datasets, the process group."""
    import torch

    from rafd.data.windows import DatasetError, open_windows
    from rafd.model.device import resolve_device
    from rafd.model.precision import check_precision
    from rafd.train.distill import load_teacher
    from rafd.train.distributed import init_distributed
    from rafd.train.trainer import plan_batches

    config = run.config
    local_world = int(os.environ.get("LOCAL_WORLD_SIZE", os.environ.get("WORLD_SIZE", "1")) or 1)
    world_size = int(os.environ.get("WORLD_SIZE", "1") or 1)
    check_precision(config.train.precision, resolve_device(config.train.device))  # fail before reading any data
    plan_batches(config.train.batch_size, world_size, config.train.micro_batch_size)
    if run.init is not None and run.resume:
        raise ValueError("--init starts a new run and --resume continues one: give one of them")
    for flag, path in (("--resume", run.out if run.resume else None), ("--init", run.init), ("--teacher", run.teacher)):
        if path is not None and not Path(path).is_file():
            raise DatasetError(f"{flag} {path} does not exist")
    teacher = load_teacher(run.teacher, config.model) if run.teacher is not None else None
    data = config.data
    train_set: Dataset[Any] = open_windows(
        run.data.root,
        list(run.data.splits),
        config.model,
        data.max_windows,
        augment=data.augment,
        cache=run.data.cache,
        estimate_poses=data.estimate_poses,
        seed=config.train.seed,
        warm_up=data.warm_up_windows,
    )
    run_meta: dict[str, Any] = {
        "recipe": run.recipe,
        "data": str(run.data.root),
        "splits": list(run.data.splits),
    }
    if run.teacher is not None:
        run_meta["teacher"] = str(run.teacher)
    if run.mix is not None:
        train_set, run_meta["mix"] = _mixed(run, run.mix, train_set)
    val_set = None
    if run.val is not None:
        val_set = open_windows(
            run.val.root,
            list(run.val.splits),
            config.model,
            data.max_val_windows,
            cache=run.val.cache,
            estimate_poses=data.estimate_poses,
            warm_up=data.warm_up_windows,
        )
    torch.set_num_threads(config.train.threads or default_threads(local_world))
    ctx = init_distributed(config.train.device, config.train.dist_timeout_minutes)
    return _Prepared(run, train_set, val_set, ctx, run_meta, teacher)


def _mixed(run: TrainRun, mix: DataSource, primary: Dataset[Any]) -> tuple[Dataset[Any], dict[str, Any]]:
    """The primary windows topped up with `mix`'s to data.mix_share of each epoch -> (dataset, what the checkpoint
    records of the mix)."""
    from rafd.data.windows import open_windows
    from rafd.train.mixing import MixedWindows

    config = run.config
    windows = open_windows(
        mix.root,
        list(mix.splits),
        config.model,
        augment=config.data.mix_augment,
        cache=mix.cache,
        estimate_poses=config.data.estimate_poses,
        seed=config.train.seed + 1,  # its windows' augmentation independent of the primary windows' with the same index
        warm_up=config.data.warm_up_windows,
    )
    mixed = MixedWindows(primary, windows, config.data.mix_share, config.train.seed)
    log.info(
        "each epoch: the %d windows of %s and %d of the %d windows of %s (share %.2f)",
        len(primary),  # type: ignore[arg-type]
        run.data.root,
        mixed.per_epoch,
        len(windows),
        mix.root,
        config.data.mix_share,
    )
    return mixed, {"data": str(mix.root), "splits": list(mix.splits), "windows_per_epoch": mixed.per_epoch}


def _fit(p: _Prepared) -> list[dict[str, Any]]:
    from rafd.train.distributed import cleanup_distributed
    from rafd.train.trainer import Trainer

    config = p.run.config
    try:
        trainer = Trainer(
            config, p.train_set, p.run.out, p.ctx, val_set=p.val_set, run_meta=p.run_meta, teacher=p.teacher
        )
        if p.run.init is not None:
            trainer.initialise_from(p.run.init)
        if p.run.resume:
            trainer.resume(p.run.out)
        log.info(
            "training recipe %s (%d frames, %d px, %s) on %d windows, %d process(es), device %s, global batch %d "
            "= %d x %d micro-batches of %d, %d DataLoader workers per process",
            p.run.recipe,
            config.model.num_frames,
            config.model.input_size,
            config.train.precision,
            len(p.train_set),  # type: ignore[arg-type]
            p.ctx.world_size,
            p.ctx.device,
            config.train.batch_size,
            p.ctx.world_size,
            trainer.plan.accumulation,
            trainer.plan.micro_batch_size,
            trainer.num_workers,
        )
        history: list[dict[str, Any]] = trainer.fit()
    finally:
        cleanup_distributed()
    return history


def process_rank() -> int:
    """This process's rank under torchrun (0 alone)."""
    return int(os.environ.get("RANK", "0") or 0)
