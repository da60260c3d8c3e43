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
import sys
from collections.abc import Sequence
from pathlib import Path

from rafd.cli.common import split_names
from rafd.config import BOX_ENCODINGS, FREEZABLE
from rafd.train.run import TrainRun


def build_parser() -> argparse.ArgumentParser:
    from rafd.train.recipes import RECIPES

    parser = argparse.ArgumentParser(
        prog="rafd-train", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", required=True, type=Path, help="data root holding sequence folders")
    parser.add_argument(
        "--split",
        required=True,
        action="append",
        help="meta.json 'set'(s) to train on: repeat or comma-separate, e.g. "
        "train_good_weather,train_good_and_bad_weather",
    )
    parser.add_argument(
        "--config",
        choices=sorted(RECIPES),
        default="tiny",
        help="; ".join(f"{r.name}: {r.description}" for r in RECIPES.values()),
    )
    parser.add_argument("--out", required=True, type=Path, help="checkpoint to write (+ .optim.pt, .history.json)")
    parser.add_argument("--cache", type=Path, help="scan cache written by rafd-prepare (default: decode the PNGs)")
    parser.add_argument(
        "--estimate-poses",
        action="store_true",
        help="run radar odometry for sequences without ego_poses.csv (slow; prefer rafd-odometry)",
    )
    recipe = parser.add_argument_group("overrides of the recipe (default: the recipe's value)")
    recipe.add_argument("--frames", type=int, choices=(1, 2, 4), help="frames per window")
    recipe.add_argument("--input-size", type=int, help="input crop in pixels")
    recipe.add_argument("--epochs", type=int)
    recipe.add_argument("--batch-size", type=int, help="GLOBAL windows per optimizer step (paper: 8)")
    recipe.add_argument(
        "--micro-batch-size",
        type=int,
        help="windows per process per forward (gradient accumulation makes up the global batch)",
    )
    recipe.add_argument("--lr", type=float)
    recipe.add_argument("--weight-decay", type=float)
    recipe.add_argument("--optimizer", choices=("adam", "adamw"))
    recipe.add_argument("--lr-schedule", choices=("constant", "cosine"))
    recipe.add_argument("--augment", action=argparse.BooleanOptionalAction, help="window-consistent flip + rotation")
    recipe.add_argument("--flow-stride", type=int, help="input pixels per flow cell (4 = the paper's)")
    recipe.add_argument("--enhance-window", type=int, help="attention window side in cells (0 = the paper's Hf/2)")
    recipe.add_argument(
        "--propagation-norm",
        choices=("post", "pre"),
        help="propagation blocks: post-norm (Deformable DETR) or pre-norm starting as the identity",
    )
    recipe.add_argument(
        "--box-encoding",
        choices=BOX_ENCODINGS,
        help="symmetric: 180-degree periodic orientation, width <= length; as_labelled: the old targets",
    )
    recipe.add_argument("--heatmap-min-overlap", type=float, help="heatmap radius overlap (CenterPoint 0.1)")
    recipe.add_argument("--heatmap-min-radius", type=int, help="heatmap radius floor in cells (CenterPoint 2)")
    parser.add_argument(
        "--precision",
        choices=("fp32", "bf16", "fp16"),
        default="fp32",
        help="bf16: autocast (several times faster on CPUs with avx512_bf16/AMX and on GPUs); "
        "fp16: autocast + gradient scaler (CUDA)",
    )
    parser.add_argument("--grad-clip", type=float, default=35.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--resume", type=Path, help="checkpoint written by rafd-train to continue from")
    parser.add_argument(
        "--init",
        type=Path,
        help="start from this checkpoint's weights where names and shapes match (e.g. a single-frame "
        "model under a 4-frame run); optimizer, schedule and epochs start fresh",
    )
    parser.add_argument(
        "--freeze",
        nargs="+",
        choices=FREEZABLE,
        default=[],
        metavar="PART",
        help=f"parts of the network that do not train ({', '.join(FREEZABLE)}): e.g. --init a "
        "single-frame model and --freeze encoder, so a 4-frame run keeps its reading of the "
        "current frame and learns only what the past adds",
    )
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
    parser.add_argument("--no-progress", dest="progress", action="store_false", help="no tqdm bar")
    return parser


def train_run(args: argparse.Namespace) -> TrainRun:
    """The flags as a TrainRun (one flag per field); repeated or comma-separated splits as one tuple."""
    values = {f.name: getattr(args, f.name) for f in dataclasses.fields(TrainRun)}
    values["split"] = split_names(args.split)
    values["val_split"] = split_names(args.val_split) if args.val_split else None
    values["freeze"] = tuple(args.freeze)
    return TrainRun(**values)


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from rafd.train.run import TrainSetupError, process_rank, train

    rank = process_rank()
    logging.basicConfig(
        level=logging.INFO if rank == 0 else logging.WARNING,
        format=f"%(asctime)s [rank {rank}] %(levelname)s %(name)s: %(message)s",
    )
    run = train_run(args)
    try:
        history = train(run)
    except TrainSetupError as error:
        print(f"rafd-train: error: {error}", file=sys.stderr)
        return 2
    if rank == 0:
        last = {k: v for k, v in history[-1].items() if k != "curve"} if history else None
        print(json.dumps({"checkpoint": str(run.out), "last_epoch": last}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
