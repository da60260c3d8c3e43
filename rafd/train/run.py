"""One training run as plain Python: `train(TrainRun(...))`. `rafd-train` builds a TrainRun from its flags (one
flag per field), and the synthetic benchmark's variants build theirs directly (rafd.bench.variants).

A run starts from a named recipe (rafd.train.recipes): every field left None keeps the recipe's value, every field
given overrides it, and the checkpoint records the result.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rafd.config import RaFDConfig
from rafd.data.augment import AugmentConfig

log = logging.getLogger("rafd.train")


@dataclass(frozen=True)
class TrainRun:
    data: Path  # data root holding sequence folders
    split: tuple[str, ...]  # meta.json splits to train on
    out: Path  # checkpoint to write (+ .optim.pt, .history.json)
    config: str = "tiny"  # recipe name (rafd.train.recipes.RECIPES)
    cache: Path | None = None  # scan cache written by rafd-prepare
    estimate_poses: bool = False  # run odometry for sequences without ego_poses.csv
    # overrides of the recipe's network (None: the recipe's)
    frames: int | None = None
    input_size: int | None = None
    flow_stride: int | None = None
    enhance_window: int | None = None
    propagation_norm: str | None = None
    box_encoding: str | None = None
    heatmap_min_overlap: float | None = None
    heatmap_min_radius: int | None = None
    no_enhancement: bool = False  # ablation: no window self-attention
    no_flow_guidance: bool = False  # ablation: vanilla deformable attention
    no_flow_supervision: bool = False  # ablation: flow loss weight 0
    # overrides of the recipe's optimisation (None: the recipe's)
    epochs: int | None = None
    batch_size: int | None = None  # GLOBAL windows per optimizer step
    micro_batch_size: int | None = None
    lr: float | None = None
    weight_decay: float | None = None
    optimizer: str | None = None
    lr_schedule: str | None = None
    augment: bool | None = None  # None: the recipe's augmentation
    # overrides of the augmentation of `data` (None: the recipe's); the mix data keep the recipe's (mix_augmentation)
    max_rotation_deg: float | None = None
    shift_max_m: float | None = None
    shift_probability: float | None = None
    num_workers: int | None = None
    max_steps_per_epoch: int | None = None
    precision: str = "fp32"
    grad_clip: float = 35.0
    seed: int = 0
    device: str = "auto"
    threads: int | None = None  # torch CPU threads per process (None: CPUs / local processes)
    log_every: int = 20
    dist_timeout: float = 30.0  # minutes
    progress: bool = True
    # where the weights start
    resume: Path | None = None  # a checkpoint of an unfinished run to continue
    init: Path | None = None  # weights to start a new run from where names and shapes match
    freeze: tuple[str, ...] = ()
    # data limits and validation
    max_windows: int | None = None
    warm_up_windows: bool = False  # also the first frames of each sequence, padded (rafd.data.RadarWindowDataset)
    val_data: Path | None = None
    val_split: tuple[str, ...] | None = None
    val_cache: Path | None = None
    val_every: int = 1
    max_val_windows: int | None = None
    # a second data root mixed into every epoch (rafd.train.mixing): e.g. simulated drives replayed under real scans
    mix_data: Path | None = None
    mix_split: tuple[str, ...] | None = None  # None: `split`
    mix_cache: Path | None = None
    mix_share: float = 0.5  # share of each epoch's windows drawn from mix_data


def model_config(run: TrainRun, base: RaFDConfig) -> RaFDConfig:
    """The recipe's network config with the run's changes."""
    changes: dict[str, Any] = {}
    if run.frames is not None:
        changes["num_frames"] = run.frames
    if run.input_size is not None:
        changes["input_size"] = run.input_size
    enhance, propagation = base.enhance, base.propagation
    if run.no_enhancement:
        enhance = dataclasses.replace(enhance, enabled=False)
    if run.enhance_window is not None:
        enhance = dataclasses.replace(enhance, window=run.enhance_window)
    if run.no_flow_guidance:
        propagation = dataclasses.replace(propagation, flow_guided=False)
    if run.propagation_norm is not None:
        propagation = dataclasses.replace(propagation, norm=run.propagation_norm)
    if enhance != base.enhance:
        changes["enhance"] = enhance
    if propagation != base.propagation:
        changes["propagation"] = propagation
    if run.flow_stride is not None:
        changes["flow"] = dataclasses.replace(base.flow, stride=run.flow_stride)
    if run.box_encoding is not None:
        changes["head"] = dataclasses.replace(base.head, box_encoding=run.box_encoding)
    targets: dict[str, Any] = {
        k: v
        for k, v in (("heatmap_min_overlap", run.heatmap_min_overlap), ("heatmap_min_radius", run.heatmap_min_radius))
        if v is not None
    }
    if targets:
        changes["targets"] = dataclasses.replace(base.targets, **targets)
    return base.replace(**changes)


def train_config(run: TrainRun, base: Any) -> Any:
    """The recipe's TrainConfig with the run's changes."""
    changes = {
        name: value
        for name, value in (
            ("epochs", run.epochs),
            ("batch_size", run.batch_size),
            ("micro_batch_size", run.micro_batch_size),
            ("lr", run.lr),
            ("weight_decay", run.weight_decay),
            ("optimizer", run.optimizer),
            ("lr_schedule", run.lr_schedule),
            ("num_workers", run.num_workers),
            ("max_steps_per_epoch", run.max_steps_per_epoch),
        )
        if value is not None
    }
    return dataclasses.replace(
        base,
        grad_clip=run.grad_clip,
        seed=run.seed,
        device=run.device,
        precision=run.precision,
        val_every=run.val_every,
        log_every=run.log_every,
        dist_timeout_minutes=run.dist_timeout,
        progress=run.progress,
        freeze=tuple(run.freeze),
        **changes,
    )


def augmentation(run: TrainRun, recipe_augment: AugmentConfig | None) -> AugmentConfig | None:
    """The augmentation of `run.data`: the recipe's; run.augment True turns it on (the default one when the recipe has
    none), False off; then the run's overrides (max_rotation_deg, shift_max_m, shift_probability)."""
    base = mix_augmentation(run, recipe_augment)
    overrides: dict[str, Any] = {
        name: value
        for name, value in (
            ("max_rotation_deg", run.max_rotation_deg),
            ("shift_max_m", run.shift_max_m),
            ("shift_probability", run.shift_probability),
        )
        if value is not None
    }
    if not overrides:
        return base
    if base is None and run.augment is False:
        raise ValueError(f"--no-augment contradicts the augmentation overrides {sorted(overrides)}")
    return dataclasses.replace(base or AugmentConfig(), **overrides)


def mix_augmentation(run: TrainRun, recipe_augment: AugmentConfig | None) -> AugmentConfig | None:
    """The augmentation of `run.mix_data`: the recipe's, turned on or off by run.augment, without the overrides, which
    fit the augmentation to the primary data (e.g. tile shifts kept inside a few real scans' labelled area) while
    the replayed simulation keeps the augmentation it was trained with."""
    if run.augment is None:
        return recipe_augment
    return (recipe_augment or AugmentConfig()) if run.augment else None


def default_threads(world_size: int) -> int:
    """CPUs this process may use (affinity, not cpu_count) shared among the local processes."""
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, cpus // max(1, world_size))


class TrainSetupError(Exception):
    """The run cannot start: its data, the recipe's changes, the starting checkpoint or the process group; the
    message says what and how to fix it. Raised before any training step."""


@dataclass(frozen=True)
class _Prepared:
    run: TrainRun
    recipe: Any  # rafd.train.recipes.Recipe
    cfg: RaFDConfig
    train_cfg: Any  # rafd.train.trainer.TrainConfig
    loss_cfg: Any  # rafd.train.losses.LossConfig
    train_set: Any
    val_set: Any
    ctx: Any  # rafd.train.distributed.DistContext
    run_meta: dict[str, Any]


def train(run: TrainRun) -> list[dict[str, Any]]:
    """Train one model as `run` says (one process, or one rank under torchrun) -> the epochs' history.

    Raises TrainSetupError before any training starts when the run cannot start."""
    from rafd.train.datasets import DatasetError

    try:
        prepared = _prepare(run)
    except (DatasetError, ValueError, RuntimeError) as error:
        raise TrainSetupError(str(error)) from error
    return _fit(prepared)


def _prepare(run: TrainRun) -> _Prepared:
    """Everything checked and opened before the first step: recipe, configs, datasets, the process group."""
    import torch

    from rafd.train.datasets import DatasetError, open_windows
    from rafd.train.distributed import init_distributed, resolve_device
    from rafd.train.losses import LossConfig
    from rafd.train.precision import check_precision
    from rafd.train.recipes import RECIPES
    from rafd.train.trainer import plan_batches

    if run.config not in RECIPES:
        raise ValueError(f"unknown recipe {run.config!r}; choose from {sorted(RECIPES)}")
    local_world = int(os.environ.get("LOCAL_WORLD_SIZE", os.environ.get("WORLD_SIZE", "1")) or 1)
    world_size = int(os.environ.get("WORLD_SIZE", "1") or 1)
    recipe = RECIPES[run.config]
    cfg = model_config(run, recipe.model)
    train_cfg = train_config(run, recipe.train)
    check_precision(train_cfg.precision, resolve_device(run.device))  # fail before reading any data
    plan_batches(train_cfg.batch_size, world_size, train_cfg.micro_batch_size)
    augment = augmentation(run, recipe.augment)
    loss_cfg = LossConfig(flow_weight=0.0 if run.no_flow_supervision else 1.0)
    if run.init is not None and run.resume is not None:
        raise ValueError("--init starts a new run and --resume continues one: give one of them")
    if run.mix_data is None and (run.mix_split is not None or run.mix_cache is not None):
        raise ValueError("--mix-split and --mix-cache describe --mix-data ROOT: give it too")
    if not 0.0 < run.mix_share < 1.0:
        raise ValueError(
            f"--mix-share is the share of each epoch's windows from --mix-data, in (0, 1); got {run.mix_share}"
        )
    for flag, path in (("--resume", run.resume), ("--init", run.init)):
        if path is not None and not Path(path).is_file():
            raise DatasetError(f"{flag} {path} does not exist")
    train_set = open_windows(
        run.data,
        list(run.split),
        cfg,
        run.max_windows,
        augment=augment,
        cache=run.cache,
        estimate_poses=run.estimate_poses,
        seed=run.seed,
        warm_up=run.warm_up_windows,
    )
    mix_meta = None
    if run.mix_data is not None:
        train_set, mix_meta = _mixed(run, cfg, train_set, mix_augmentation(run, recipe.augment))
    val_set = None
    if run.val_data is not None or run.val_split is not None:
        val_root = run.val_data if run.val_data is not None else run.data
        val_cache = run.val_cache if run.val_cache is not None else (run.cache if val_root == run.data else None)
        val_set = open_windows(
            val_root,
            list(run.val_split or ("test",)),
            cfg,
            run.max_val_windows,
            cache=val_cache,
            estimate_poses=run.estimate_poses,
            warm_up=run.warm_up_windows,
        )
    torch.set_num_threads(run.threads or default_threads(local_world))
    ctx = init_distributed(run.device, train_cfg.dist_timeout_minutes)
    run_meta = {
        "recipe": recipe.name,
        "data": str(run.data),
        "splits": list(run.split),
        "augment": None if augment is None else dataclasses.asdict(augment),
        "precision": train_cfg.precision,
    }
    if mix_meta is not None:
        run_meta["mix"] = mix_meta
    return _Prepared(run, recipe, cfg, train_cfg, loss_cfg, train_set, val_set, ctx, run_meta)


def _mixed(run: TrainRun, cfg: RaFDConfig, primary: Any, augment: AugmentConfig | None) -> tuple[Any, dict[str, Any]]:
    """The primary windows topped up with run.mix_data's to run.mix_share of each epoch -> (dataset, what the
    checkpoint records of the mix)."""
    from rafd.train.datasets import open_windows
    from rafd.train.mixing import MixedWindows

    splits = list(run.mix_split or run.split)
    mix = open_windows(
        run.mix_data,  # type: ignore[arg-type]
        splits,
        cfg,
        augment=augment,
        cache=run.mix_cache,
        estimate_poses=run.estimate_poses,
        seed=run.seed + 1,  # its windows' augmentation independent of the primary windows' with the same index
        warm_up=run.warm_up_windows,
    )
    mixed = MixedWindows(primary, mix, run.mix_share, run.seed)
    log.info(
        "each epoch: the %d windows of %s and %d of the %d windows of %s (share %.2f)",
        len(primary),
        run.data,
        mixed.per_epoch,
        len(mix),
        run.mix_data,
        run.mix_share,
    )
    meta = {
        "data": str(run.mix_data),
        "splits": splits,
        "share": run.mix_share,
        "windows_per_epoch": mixed.per_epoch,
        "augment": None if augment is None else dataclasses.asdict(augment),
    }
    return mixed, meta


def _fit(p: _Prepared) -> list[dict[str, Any]]:
    from rafd.train.distributed import cleanup_distributed
    from rafd.train.trainer import Trainer

    try:
        trainer = Trainer(
            p.cfg,
            p.train_cfg,
            p.train_set,
            p.run.out,
            p.ctx,
            loss_cfg=p.loss_cfg,
            val_set=p.val_set,
            run_meta=p.run_meta,
        )
        if p.run.init is not None:
            trainer.initialise_from(p.run.init)
        if p.run.resume is not None:
            trainer.resume(p.run.resume)
        log.info(
            "training recipe %s (%d frames, %d px, %s) on %d windows, %d process(es), device %s, global batch %d "
            "= %d x %d micro-batches of %d, %d DataLoader workers per process",
            p.recipe.name,
            p.cfg.num_frames,
            p.cfg.input_size,
            p.train_cfg.precision,
            len(p.train_set),
            p.ctx.world_size,
            p.ctx.device,
            p.train_cfg.batch_size,
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
