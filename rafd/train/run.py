"""One training run as plain Python: `train(TrainRun(...))`. `rafd train` makes one flag per TrainRun field
(rafd.cli.train: the help is the field's metadata), and the synthetic benchmark's variants build theirs directly
(bench.variants).

A run starts from a named recipe (rafd.train.recipes): every field left None keeps the recipe's value, every field
given overrides it, and the checkpoint records the result. A field named as a TrainConfig field
(rafd.train.trainer, where the training defaults are written once) overrides that field; the others choose the
data, the network's changes and where the weights start.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rafd.config import RaFDConfig
from rafd.cpu import usable_cpus
from rafd.data.augment import AugmentConfig

log = logging.getLogger("rafd.train")

# The flag groups of `rafd train` (a field's metadata "group"; none: the main group).
RECIPE_GROUP = "overrides of the recipe (default: the recipe's value)"
MIX_GROUP = "a second data root mixed into every epoch (e.g. simulated drives replayed while fine-tuning on real scans)"


def setting(default: Any = None, help: str = "", group: str | None = None, metavar: str | None = None) -> Any:
    """A TrainRun field with what its `rafd train` flag says in its metadata: help, group and metavar."""
    return field(default=default, metadata={"help": help, "group": group, "metavar": metavar})


@dataclass(frozen=True)
class TrainRun:
    data: Path = setting(dataclasses.MISSING, "data root holding sequence folders", metavar="ROOT")
    split: tuple[str, ...] = setting(dataclasses.MISSING, "the splits to train on")
    out: Path = setting(dataclasses.MISSING, "checkpoint to write (+ .optim.pt, .history.json)", metavar="CKPT")
    config: str = setting("tiny", "the recipe the run starts from (a name of rafd.train.recipes.RECIPES)")
    cache: Path | None = setting(None, "scan cache written by rafd prepare (default: decode the PNGs)")
    estimate_poses: bool = setting(
        False, "run radar odometry for sequences without ego_poses.csv (slow; prefer rafd odometry)"
    )
    # overrides of the recipe's network
    frames: int | None = setting(None, "frames per window (the model's T)", RECIPE_GROUP)
    input_size: int | None = setting(None, "side in pixels of the model's input crop", RECIPE_GROUP, "PX")
    flow_stride: int | None = setting(None, "input pixels per flow cell (4 = the paper's)", RECIPE_GROUP)
    enhance_window: int | None = setting(None, "attention window side in cells (0 = the paper's Hf/2)", RECIPE_GROUP)
    propagation_norm: str | None = setting(
        None, "propagation blocks: post-norm (Deformable DETR) or pre-norm starting as the identity", RECIPE_GROUP
    )
    box_encoding: str | None = setting(
        None, "symmetric: 180-degree periodic orientation, width <= length; as_labelled: the old targets", RECIPE_GROUP
    )
    heatmap_min_overlap: float | None = setting(None, "heatmap radius overlap (CenterPoint 0.1)", RECIPE_GROUP)
    heatmap_min_radius: int | None = setting(None, "heatmap radius floor in cells (CenterPoint 2)", RECIPE_GROUP)
    no_enhancement: bool = setting(False, "ablation: no window self-attention")
    no_flow_guidance: bool = setting(False, "ablation: vanilla deformable attention")
    no_flow_supervision: bool = setting(False, "ablation: flow loss weight 0")
    # overrides of the recipe's optimisation
    epochs: int | None = setting(None, "epochs to train", RECIPE_GROUP)
    batch_size: int | None = setting(None, "GLOBAL windows per optimizer step (paper: 8)", RECIPE_GROUP)
    micro_batch_size: int | None = setting(
        None, "windows per process per forward (gradient accumulation makes up the global batch)", RECIPE_GROUP
    )
    lr: float | None = setting(None, "learning rate", RECIPE_GROUP)
    weight_decay: float | None = setting(None, "weight decay", RECIPE_GROUP)
    optimizer: str | None = setting(None, "optimizer", RECIPE_GROUP)
    lr_schedule: str | None = setting(None, "learning-rate schedule over the epochs", RECIPE_GROUP)
    augment: bool | None = setting(None, "window-consistent flip + rotation", RECIPE_GROUP)
    # overrides of the augmentation of `data`; the mix data keep the recipe's (mix_augmentation)
    max_rotation_deg: float | None = setting(
        None,
        "ROOT's windows turn by up to +-DEG about the crop's centre (180: any bearing; not the --mix-data's)",
        RECIPE_GROUP,
        "DEG",
    )
    shift_max_m: float | None = setting(
        None,
        "ROOT's crops are cut around a point up to M metres from the radar (full-scan tiles; keep it inside the "
        "labelled area of a few labelled scans; not the --mix-data's)",
        RECIPE_GROUP,
        "M",
    )
    shift_probability: float | None = setting(
        None, "the share of ROOT's windows cut away from the radar (not the --mix-data's)", RECIPE_GROUP, "P"
    )
    num_workers: int | None = setting(None, "DataLoader workers per process (default: 4 on CUDA, 0 on CPU)")
    max_steps_per_epoch: int | None = setting(None, "cap optimizer steps per epoch (smoke runs)")
    # how it runs (None: the recipe's, i.e. TrainConfig's defaults)
    precision: str | None = setting(
        None,
        "bf16: autocast (several times faster on CPUs with avx512_bf16/AMX and on GPUs); "
        "fp16: autocast + gradient scaler (CUDA)",
    )
    grad_clip: float | None = setting(None, "gradient norm clip (0: none)")
    seed: int | None = setting(None, "seed of the weights, the data order and augmentation")
    device: str | None = setting(None, "torch device")
    threads: int | None = setting(None, "torch's CPU threads per process (default: CPUs / processes)")
    log_every: int | None = setting(None, "optimizer steps between loss logs")
    dist_timeout: float | None = setting(None, "process-group timeout in minutes")
    progress: bool | None = setting(None, "progress bars")
    # where the weights start
    resume: Path | None = setting(None, "the same command again after an interruption (the flags must match the run's)")
    init: Path | None = setting(
        None,
        "start from this checkpoint's weights where names and shapes match (e.g. a single-frame model under a "
        "4-frame run); optimizer, schedule and epochs start fresh",
    )
    freeze: tuple[str, ...] = setting(
        (),
        "parts of the network that do not train: e.g. --init a single-frame model and --freeze encoder, so a "
        "4-frame run keeps its reading of the current frame and learns only what the past adds",
        metavar="PART",
    )
    # data limits and validation
    max_windows: int | None = setting(None, "use at most N (evenly spaced) training windows")
    warm_up_windows: bool = setting(False, "also the first frames of each sequence, padded (RadarWindowDataset)")
    val_data: Path | None = setting(None, "validation data root (default: none)", metavar="ROOT")
    val_split: tuple[str, ...] | None = setting(None, "validation splits (default: test)")
    val_cache: Path | None = setting(None, "scan cache of the validation root (default: --cache)")
    val_every: int | None = setting(None, "validate every N epochs (0: never)")
    max_val_windows: int | None = setting(None, "use at most N validation windows")
    # a second data root mixed into every epoch (rafd.train.mixing)
    mix_data: Path | None = setting(
        None,
        "every epoch holds each window of ROOT once plus windows of ROOT2 up to --mix-share of the epoch "
        "(ROOT2's windows in turn over the epochs, augmented as the recipe says)",
        MIX_GROUP,
        "ROOT2",
    )
    mix_split: tuple[str, ...] | None = setting(None, "ROOT2's splits (default: --split)", MIX_GROUP)
    mix_cache: Path | None = setting(None, "scan cache of ROOT2 (rafd prepare)", MIX_GROUP, "CACHE")
    mix_share: float = setting(
        0.5,
        "share of each epoch's windows drawn from ROOT2, in (0, 1); a half: as many as ROOT has",
        MIX_GROUP,
        "FRACTION",
    )


# TrainRun fields that override a TrainConfig field of another name.
TRAIN_CONFIG_NAMES = {"dist_timeout": "dist_timeout_minutes"}


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
    """The recipe's TrainConfig with the run's changes: every field of the run named as one of TrainConfig's
    (TRAIN_CONFIG_NAMES: of another name) and not None."""
    names = {f.name for f in dataclasses.fields(base)}
    changes = {
        TRAIN_CONFIG_NAMES.get(f.name, f.name): getattr(run, f.name)
        for f in dataclasses.fields(run)
        if TRAIN_CONFIG_NAMES.get(f.name, f.name) in names and getattr(run, f.name) is not None
    }
    changes["freeze"] = tuple(run.freeze)  # a list given from Python becomes the tuple the config holds
    return dataclasses.replace(base, **changes)


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
    """CPUs this process may use (rafd.cpu.usable_cpus) shared among the local processes."""
    return max(1, usable_cpus() // max(1, world_size))


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
    from rafd.data.windows import DatasetError

    try:
        prepared = _prepare(run)
    except (DatasetError, ValueError, RuntimeError) as error:
        raise TrainSetupError(str(error)) from error
    return _fit(prepared)


def _prepare(run: TrainRun) -> _Prepared:
    """Everything checked and opened before the first step: recipe, configs, datasets, the process group."""
    import torch

    from rafd.data.windows import DatasetError, open_windows
    from rafd.model.device import resolve_device
    from rafd.model.precision import check_precision
    from rafd.train.distributed import init_distributed
    from rafd.train.losses import LossConfig
    from rafd.train.recipes import RECIPES
    from rafd.train.trainer import plan_batches

    if run.config not in RECIPES:
        raise ValueError(f"unknown recipe {run.config!r}; choose from {sorted(RECIPES)}")
    local_world = int(os.environ.get("LOCAL_WORLD_SIZE", os.environ.get("WORLD_SIZE", "1")) or 1)
    world_size = int(os.environ.get("WORLD_SIZE", "1") or 1)
    recipe = RECIPES[run.config]
    cfg = model_config(run, recipe.model)
    train_cfg = train_config(run, recipe.train)
    check_precision(train_cfg.precision, resolve_device(train_cfg.device))  # fail before reading any data
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
        seed=train_cfg.seed,
        warm_up=run.warm_up_windows,
    )
    mix_meta = None
    if run.mix_data is not None:
        train_set, mix_meta = _mixed(run, cfg, train_set, mix_augmentation(run, recipe.augment), train_cfg.seed)
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
    ctx = init_distributed(train_cfg.device, train_cfg.dist_timeout_minutes)
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


def _mixed(
    run: TrainRun, cfg: RaFDConfig, primary: Any, augment: AugmentConfig | None, seed: int
) -> tuple[Any, dict[str, Any]]:
    """The primary windows topped up with run.mix_data's to run.mix_share of each epoch (`seed`: the run's) ->
    (dataset, what the checkpoint records of the mix)."""
    from rafd.data.windows import open_windows
    from rafd.train.mixing import MixedWindows

    splits = list(run.mix_split or run.split)
    mix = open_windows(
        run.mix_data,  # type: ignore[arg-type]
        splits,
        cfg,
        augment=augment,
        cache=run.mix_cache,
        estimate_poses=run.estimate_poses,
        seed=seed + 1,  # its windows' augmentation independent of the primary windows' with the same index
        warm_up=run.warm_up_windows,
    )
    mixed = MixedWindows(primary, mix, run.mix_share, seed)
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
