"""rafd-train: train RaFD on a RADIATE-layout data root (single process or under torchrun)."""
from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import sys
from pathlib import Path
from typing import Sequence

from rafd.config import RaFDConfig

log = logging.getLogger("rafd.train")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="rafd-train", description=__doc__)
    parser.add_argument("--data", required=True, type=Path, help="data root holding sequence folders")
    parser.add_argument("--split", required=True, help="meta.json 'set' to train on, e.g. train_good_weather")
    parser.add_argument("--config", choices=("tiny", "paper"), default="tiny", help="network size")
    parser.add_argument("--frames", type=int, choices=(1, 2, 4), default=4, help="frames per window")
    parser.add_argument("--out", required=True, type=Path, help="checkpoint to write (+ .optim.pt, .history.json)")
    parser.add_argument("--epochs", type=int, default=10)
    parser.add_argument("--batch-size", type=int, default=8, help="per process")
    parser.add_argument("--lr", type=float, default=2e-4)
    parser.add_argument("--weight-decay", type=float, default=1e-2)
    parser.add_argument("--optimizer", choices=("adamw", "adam"), default="adamw")
    parser.add_argument("--lr-schedule", choices=("constant", "cosine"), default="constant")
    parser.add_argument("--grad-clip", type=float, default=35.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--resume", type=Path, help="checkpoint written by rafd-train to continue from")
    parser.add_argument("--device", default="auto", help="cpu | cuda | cuda:N | auto")
    parser.add_argument("--val-data", type=Path, help="validation data root (default: none)")
    parser.add_argument("--val-split", help="validation split (default: --split's name under --val-data)")
    parser.add_argument("--val-every", type=int, default=1, help="validate every N epochs (0: never)")
    parser.add_argument("--no-enhancement", action="store_true", help="ablation: no window self-attention")
    parser.add_argument("--no-flow-supervision", action="store_true", help="ablation: flow loss weight 0")
    parser.add_argument("--no-flow-guidance", action="store_true", help="ablation: vanilla deformable attention")
    parser.add_argument("--no-augment", action="store_true", help="disable training augmentation")
    parser.add_argument("--input-size", type=int, help="override the config's input crop (pixels)")
    parser.add_argument("--max-windows", type=int, help="use at most N (evenly spaced) training windows")
    parser.add_argument("--max-val-windows", type=int, help="use at most N validation windows")
    parser.add_argument("--max-steps-per-epoch", type=int, help="cap optimizer steps per epoch (smoke runs)")
    parser.add_argument("--num-workers", type=int, default=0, help="DataLoader workers per process")
    parser.add_argument("--threads", type=int, help="torch CPU threads per process (default: CPUs / processes)")
    parser.add_argument("--no-progress", action="store_true", help="no tqdm bar")
    return parser


def model_config(args: argparse.Namespace) -> RaFDConfig:
    """--config/--frames/--input-size/ablation flags -> RaFDConfig."""
    base = RaFDConfig.tiny() if args.config == "tiny" else RaFDConfig.paper()
    changes: dict[str, object] = {"num_frames": args.frames}
    if args.input_size is not None:
        changes["input_size"] = args.input_size
    if args.no_enhancement:
        changes["enhance"] = dataclasses.replace(base.enhance, enabled=False)
    if args.no_flow_guidance:
        changes["propagation"] = dataclasses.replace(base.propagation, flow_guided=False)
    return base.replace(**changes)


def default_threads(world_size: int) -> int:
    """CPUs this process may use (affinity, not cpu_count) shared among the local processes."""
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, cpus // max(1, world_size))


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    import torch

    from rafd.train.datasets import DatasetError, open_windows
    from rafd.train.distributed import cleanup_distributed, init_distributed
    from rafd.train.losses import LossConfig
    from rafd.train.trainer import Trainer, TrainConfig

    world_size = int(os.environ.get("WORLD_SIZE", "1") or 1)
    rank = int(os.environ.get("RANK", "0") or 0)
    logging.basicConfig(
        level=logging.INFO if rank == 0 else logging.WARNING,
        format=f"%(asctime)s [rank {rank}] %(levelname)s %(name)s: %(message)s",
    )
    try:
        cfg = model_config(args)
        train_cfg = TrainConfig(
            epochs=args.epochs,
            batch_size=args.batch_size,
            lr=args.lr,
            weight_decay=args.weight_decay,
            optimizer=args.optimizer,
            lr_schedule=args.lr_schedule,
            grad_clip=args.grad_clip,
            seed=args.seed,
            device=args.device,
            num_workers=args.num_workers,
            val_every=args.val_every,
            max_steps_per_epoch=args.max_steps_per_epoch,
            progress=not args.no_progress,
        )
        loss_cfg = LossConfig(flow_weight=0.0 if args.no_flow_supervision else 1.0)
        if args.resume is not None and not args.resume.is_file():
            raise DatasetError(f"--resume {args.resume} does not exist")
        train_set = open_windows(args.data, args.split, cfg, args.max_windows, augment=not args.no_augment)
        val_set = None
        if args.val_data is not None or args.val_split is not None:
            val_root = args.val_data if args.val_data is not None else args.data
            val_split = args.val_split if args.val_split is not None else args.split
            val_set = open_windows(val_root, val_split, cfg, args.max_val_windows, augment=False)
    except (DatasetError, ValueError) as error:
        print(f"rafd-train: error: {error}", file=sys.stderr)
        return 2

    torch.set_num_threads(args.threads or default_threads(world_size))
    try:
        ctx = init_distributed(args.device)
    except RuntimeError as error:
        print(f"rafd-train: error: {error}", file=sys.stderr)
        return 2
    try:
        trainer = Trainer(cfg, train_cfg, train_set, args.out, ctx, loss_cfg=loss_cfg, val_set=val_set)
        if args.resume is not None:
            trainer.resume(args.resume)
        log.info(
            "training %s (%d frames, %d px) on %d windows, %d process(es), device %s",
            args.config, cfg.num_frames, cfg.input_size, len(train_set), ctx.world_size, ctx.device,
        )
        history = trainer.fit()
    finally:
        cleanup_distributed()
    if ctx.is_main:
        print(json.dumps({"checkpoint": str(args.out), "last_epoch": history[-1] if history else None}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
