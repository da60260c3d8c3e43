"""rafd-train: train RaFD on a RADIATE-layout data root (one process, or several under torchrun).

`--config NAME` picks a recipe (rafd.train.recipes: `paper` = the paper's setting, `tiny` = the CPU-sized one);
every flag given overrides the recipe's value, and the checkpoint records the result. Prepare the data once first:
`rafd-odometry ROOT` (ego poses) and `rafd-prepare ROOT CACHE` (decoded crops; then pass --cache CACHE).
`--batch-size` is the global batch (over all processes), as in the paper.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import sys
from pathlib import Path
from typing import Sequence

from rafd.augment import AugmentConfig
from rafd.config import BOX_ENCODINGS, FREEZABLE, RaFDConfig

log = logging.getLogger("rafd.train")


def build_parser() -> argparse.ArgumentParser:
    from rafd.train.recipes import RECIPES

    parser = argparse.ArgumentParser(prog="rafd-train", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", required=True, type=Path, help="data root holding sequence folders")
    parser.add_argument("--split", required=True, action="append",
                        help="meta.json 'set'(s) to train on: repeat or comma-separate, e.g. "
                             "train_good_weather,train_good_and_bad_weather")
    parser.add_argument("--config", choices=sorted(RECIPES), default="tiny",
                        help="; ".join(f"{r.name}: {r.description}" for r in RECIPES.values()))
    parser.add_argument("--out", required=True, type=Path, help="checkpoint to write (+ .optim.pt, .history.json)")
    parser.add_argument("--cache", type=Path, help="scan cache written by rafd-prepare (default: decode the PNGs)")
    parser.add_argument("--estimate-poses", action="store_true",
                        help="run radar odometry for sequences without ego_poses.csv (slow; prefer rafd-odometry)")
    recipe = parser.add_argument_group("overrides of the recipe (default: the recipe's value)")
    recipe.add_argument("--frames", type=int, choices=(1, 2, 4), help="frames per window")
    recipe.add_argument("--input-size", type=int, help="input crop in pixels")
    recipe.add_argument("--epochs", type=int)
    recipe.add_argument("--batch-size", type=int, help="GLOBAL windows per optimizer step (paper: 8)")
    recipe.add_argument("--micro-batch-size", type=int,
                        help="windows per process per forward (gradient accumulation makes up the global batch)")
    recipe.add_argument("--lr", type=float)
    recipe.add_argument("--weight-decay", type=float)
    recipe.add_argument("--optimizer", choices=("adam", "adamw"))
    recipe.add_argument("--lr-schedule", choices=("constant", "cosine"))
    recipe.add_argument("--augment", action=argparse.BooleanOptionalAction, help="window-consistent flip + rotation")
    recipe.add_argument("--flow-stride", type=int, help="input pixels per flow cell (4 = the paper's)")
    recipe.add_argument("--enhance-window", type=int, help="attention window side in cells (0 = the paper's Hf/2)")
    recipe.add_argument("--propagation-norm", choices=("post", "pre"),
                        help="propagation blocks: post-norm (Deformable DETR) or pre-norm starting as the identity")
    recipe.add_argument("--box-encoding", choices=BOX_ENCODINGS,
                        help="symmetric: 180-degree periodic orientation, width <= length; as_labelled: the old targets")
    recipe.add_argument("--heatmap-min-overlap", type=float, help="heatmap radius overlap (CenterPoint 0.1)")
    recipe.add_argument("--heatmap-min-radius", type=int, help="heatmap radius floor in cells (CenterPoint 2)")
    parser.add_argument("--precision", choices=("fp32", "bf16", "fp16"), default="fp32",
                        help="bf16: autocast (several times faster on CPUs with avx512_bf16/AMX and on GPUs); "
                             "fp16: autocast + gradient scaler (CUDA)")
    parser.add_argument("--grad-clip", type=float, default=35.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--resume", type=Path, help="checkpoint written by rafd-train to continue from")
    parser.add_argument("--init", type=Path,
                        help="start from this checkpoint's weights where names and shapes match (e.g. a single-frame "
                             "model under a 4-frame run); optimizer, schedule and epochs start fresh")
    parser.add_argument("--freeze", nargs="+", choices=FREEZABLE, default=[], metavar="PART",
                        help=f"parts of the network that do not train ({', '.join(FREEZABLE)}): e.g. --init a "
                             "single-frame model and --freeze encoder, so a 4-frame run keeps its reading of the "
                             "current frame and learns only what the past adds")
    parser.add_argument("--device", default="auto", help="cpu | cuda | cuda:N | auto")
    parser.add_argument("--val-data", type=Path, help="validation data root (default: none)")
    parser.add_argument("--val-split", action="append", help="validation split(s) (default: test)")
    parser.add_argument("--val-cache", type=Path, help="scan cache of the validation root (default: --cache)")
    parser.add_argument("--val-every", type=int, default=1, help="validate every N epochs (0: never)")
    parser.add_argument("--no-enhancement", action="store_true", help="ablation: no window self-attention")
    parser.add_argument("--no-flow-supervision", action="store_true", help="ablation: flow loss weight 0")
    parser.add_argument("--no-flow-guidance", action="store_true", help="ablation: vanilla deformable attention")
    parser.add_argument("--max-windows", type=int, help="use at most N (evenly spaced) training windows")
    parser.add_argument("--max-val-windows", type=int, help="use at most N validation windows")
    parser.add_argument("--max-steps-per-epoch", type=int, help="cap optimizer steps per epoch (smoke runs)")
    parser.add_argument("--num-workers", type=int, help="DataLoader workers per process (default: 4 on CUDA, 0 on CPU)")
    parser.add_argument("--threads", type=int, help="torch CPU threads per process (default: CPUs / processes)")
    parser.add_argument("--log-every", type=int, default=20, help="optimizer steps between loss logs")
    parser.add_argument("--dist-timeout", type=float, default=30.0, help="process-group timeout in minutes")
    parser.add_argument("--no-progress", action="store_true", help="no tqdm bar")
    return parser


def model_config(args: argparse.Namespace, base: RaFDConfig) -> RaFDConfig:
    """The recipe's network config with the command line's changes."""
    changes: dict[str, object] = {}
    if args.frames is not None:
        changes["num_frames"] = args.frames
    if args.input_size is not None:
        changes["input_size"] = args.input_size
    if args.no_enhancement:
        changes["enhance"] = dataclasses.replace(base.enhance, enabled=False)
    if args.no_flow_guidance:
        changes["propagation"] = dataclasses.replace(base.propagation, flow_guided=False)
    if args.propagation_norm is not None:
        changes["propagation"] = dataclasses.replace(changes.get("propagation", base.propagation),
                                                     norm=args.propagation_norm)
    if args.flow_stride is not None:
        changes["flow"] = dataclasses.replace(base.flow, stride=args.flow_stride)
    if args.enhance_window is not None:
        changes["enhance"] = dataclasses.replace(changes.get("enhance", base.enhance), window=args.enhance_window)
    if args.box_encoding is not None:
        changes["head"] = dataclasses.replace(base.head, box_encoding=args.box_encoding)
    targets = {k: v for k, v in (("heatmap_min_overlap", args.heatmap_min_overlap),
                                 ("heatmap_min_radius", args.heatmap_min_radius)) if v is not None}
    if targets:
        changes["targets"] = dataclasses.replace(base.targets, **targets)
    return base.replace(**changes)


def train_config(args: argparse.Namespace, base):
    """The recipe's TrainConfig with the command line's changes."""
    changes = {field: value for field, value in (
        ("epochs", args.epochs), ("batch_size", args.batch_size), ("micro_batch_size", args.micro_batch_size),
        ("lr", args.lr), ("weight_decay", args.weight_decay), ("optimizer", args.optimizer),
        ("lr_schedule", args.lr_schedule), ("num_workers", args.num_workers),
        ("max_steps_per_epoch", args.max_steps_per_epoch)) if value is not None}
    return dataclasses.replace(base, grad_clip=args.grad_clip, seed=args.seed, device=args.device,
                               precision=args.precision, val_every=args.val_every, log_every=args.log_every,
                               dist_timeout_minutes=args.dist_timeout, progress=not args.no_progress,
                               freeze=tuple(args.freeze), **changes)


def default_threads(world_size: int) -> int:
    """CPUs this process may use (affinity, not cpu_count) shared among the local processes."""
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, cpus // max(1, world_size))


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    import torch

    from rafd.train.datasets import DatasetError, open_windows
    from rafd.train.distributed import cleanup_distributed, init_distributed, resolve_device
    from rafd.train.losses import LossConfig
    from rafd.train.precision import check_precision
    from rafd.train.recipes import RECIPES
    from rafd.train.trainer import Trainer, plan_batches

    local_world = int(os.environ.get("LOCAL_WORLD_SIZE", os.environ.get("WORLD_SIZE", "1")) or 1)
    world_size = int(os.environ.get("WORLD_SIZE", "1") or 1)
    rank = int(os.environ.get("RANK", "0") or 0)
    logging.basicConfig(
        level=logging.INFO if rank == 0 else logging.WARNING,
        format=f"%(asctime)s [rank {rank}] %(levelname)s %(name)s: %(message)s",
    )
    recipe = RECIPES[args.config]
    try:
        cfg = model_config(args, recipe.model)
        train_cfg = train_config(args, recipe.train)
        check_precision(train_cfg.precision, resolve_device(args.device))  # fail before reading any data
        plan_batches(train_cfg.batch_size, world_size, train_cfg.micro_batch_size)
        augment = recipe.augment if args.augment is None else (recipe.augment or AugmentConfig()) if args.augment else None
        loss_cfg = LossConfig(flow_weight=0.0 if args.no_flow_supervision else 1.0)
        if args.resume is not None and not args.resume.is_file():
            raise DatasetError(f"--resume {args.resume} does not exist")
        if args.init is not None and args.resume is not None:
            raise ValueError("--init starts a new run and --resume continues one: give one of them")
        if args.init is not None and not args.init.is_file():
            raise DatasetError(f"--init {args.init} does not exist")
        train_set = open_windows(args.data, args.split, cfg, args.max_windows, augment=augment, cache=args.cache,
                                 estimate_poses=args.estimate_poses, seed=args.seed)
        val_set = None
        if args.val_data is not None or args.val_split is not None:
            val_root = args.val_data if args.val_data is not None else args.data
            val_cache = args.val_cache if args.val_cache is not None else (args.cache if val_root == args.data else None)
            val_set = open_windows(val_root, args.val_split or ["test"], cfg, args.max_val_windows, cache=val_cache,
                                   estimate_poses=args.estimate_poses)
    except (DatasetError, ValueError, RuntimeError) as error:
        print(f"rafd-train: error: {error}", file=sys.stderr)
        return 2

    torch.set_num_threads(args.threads or default_threads(local_world))
    try:
        ctx = init_distributed(args.device, train_cfg.dist_timeout_minutes)
    except RuntimeError as error:
        print(f"rafd-train: error: {error}", file=sys.stderr)
        return 2
    run_meta = {"recipe": recipe.name, "data": str(args.data), "splits": args.split,
                "augment": None if augment is None else dataclasses.asdict(augment), "precision": train_cfg.precision}
    try:
        trainer = Trainer(cfg, train_cfg, train_set, args.out, ctx, loss_cfg=loss_cfg, val_set=val_set,
                          run_meta=run_meta)
        if args.init is not None:
            trainer.initialise_from(args.init)
        if args.resume is not None:
            trainer.resume(args.resume)
        log.info(
            "training recipe %s (%d frames, %d px, %s) on %d windows, %d process(es), device %s, global batch %d "
            "= %d x %d micro-batches of %d, %d DataLoader workers per process",
            recipe.name, cfg.num_frames, cfg.input_size, train_cfg.precision, len(train_set), ctx.world_size,
            ctx.device, train_cfg.batch_size, ctx.world_size, trainer.plan.accumulation,
            trainer.plan.micro_batch_size, trainer.num_workers,
        )
        history = trainer.fit()
    finally:
        cleanup_distributed()
    if ctx.is_main:
        last = {k: v for k, v in history[-1].items() if k != "curve"} if history else None
        print(json.dumps({"checkpoint": str(args.out), "last_epoch": last}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
