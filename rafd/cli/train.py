"""rafd train: train RaFD on a RADIATE-layout data root (one process, or several under torchrun).

`--config NAME` picks a recipe (rafd.train.recipes: `paper` = the paper's setting, `tiny` = the CPU-sized one);
every flag given overrides the recipe's value, and the checkpoint records the result. Prepare the data once first:
`rafd odometry ROOT` (ego poses) and `rafd prepare ROOT --out CACHE` (decoded crops; then pass --cache CACHE).
`--batch-size` is the global batch (over all processes), as in the paper. An interrupted run goes on with the same
command and `--resume`.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
from collections.abc import Sequence
from pathlib import Path

from rafd.cli import flags
from rafd.config import BOX_ENCODINGS, FREEZABLE
from rafd.train.run import TrainRun


def build_parser() -> argparse.ArgumentParser:
    from rafd.train.recipes import RECIPES

    parser = argparse.ArgumentParser(
        prog=flags.prog("train"), description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("data", nargs="?", type=Path, metavar="ROOT", help="data root holding sequence folders")
    flags.add_split(parser, "the splits to train on", required=True)
    flags.add_config(parser, RECIPES, "tiny", "; ".join(f"{r.name}: {r.description}" for r in RECIPES.values()))
    flags.add_out(parser, "CKPT", "checkpoint to write (+ .optim.pt, .history.json)", required=True)
    parser.add_argument("--cache", type=Path, help="scan cache written by rafd prepare (default: decode the PNGs)")
    parser.add_argument(
        "--estimate-poses",
        action="store_true",
        help="run radar odometry for sequences without ego_poses.csv (slow; prefer rafd odometry)",
    )
    recipe = parser.add_argument_group("overrides of the recipe (default: the recipe's value)")
    flags.add_window_frames(recipe, choices=(1, 2, 4))
    recipe.add_argument("--input-size", type=int, metavar="PX", help="side in pixels of the model's input crop")
    recipe.add_argument("--epochs", type=int, help="epochs to train")
    recipe.add_argument("--batch-size", type=int, help="GLOBAL windows per optimizer step (paper: 8)")
    recipe.add_argument(
        "--micro-batch-size",
        type=int,
        help="windows per process per forward (gradient accumulation makes up the global batch)",
    )
    recipe.add_argument("--lr", type=float, help="learning rate")
    recipe.add_argument("--weight-decay", type=float, help="weight decay")
    recipe.add_argument("--optimizer", choices=("adam", "adamw"), help="optimizer")
    recipe.add_argument("--lr-schedule", choices=("constant", "cosine"), help="learning-rate schedule over the epochs")
    recipe.add_argument("--augment", action=argparse.BooleanOptionalAction, help="window-consistent flip + rotation")
    recipe.add_argument(
        "--max-rotation-deg",
        type=float,
        metavar="DEG",
        help="ROOT's windows turn by up to +-DEG about the crop's centre (180: any bearing; not the --mix-data's)",
    )
    recipe.add_argument(
        "--shift-max-m",
        type=float,
        metavar="M",
        help="ROOT's crops are cut around a point up to M metres from the radar (full-scan tiles; keep it inside "
        "the labelled area of a few labelled scans; not the --mix-data's)",
    )
    recipe.add_argument(
        "--shift-probability",
        type=float,
        metavar="P",
        help="the share of ROOT's windows cut away from the radar (not the --mix-data's)",
    )
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
    parser.add_argument("--grad-clip", type=float, default=35.0, help="gradient norm clip (default %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the weights, the data order and augmentation")
    flags.add_resume(parser, "the same command again after an interruption (the flags must match the run's)")
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
    flags.add_device(parser)
    parser.add_argument("--val-data", type=Path, metavar="ROOT", help="validation data root (default: none)")
    flags.add_split(parser, "validation splits (default: test)", flag="--val-split")
    parser.add_argument("--val-cache", type=Path, help="scan cache of the validation root (default: --cache)")
    parser.add_argument("--val-every", type=int, default=1, help="validate every N epochs (0: never)")
    parser.add_argument("--no-enhancement", action="store_true", help="ablation: no window self-attention")
    parser.add_argument("--no-flow-supervision", action="store_true", help="ablation: flow loss weight 0")
    parser.add_argument("--no-flow-guidance", action="store_true", help="ablation: vanilla deformable attention")
    parser.add_argument("--max-windows", type=int, help="use at most N (evenly spaced) training windows")
    flags.add_warm_up_windows(parser)
    parser.add_argument("--max-val-windows", type=int, help="use at most N validation windows")
    mix = parser.add_argument_group(
        "a second data root mixed into every epoch (e.g. simulated drives replayed while fine-tuning on real scans)"
    )
    mix.add_argument(
        "--mix-data",
        type=Path,
        metavar="ROOT2",
        help="every epoch holds each window of ROOT once plus windows of ROOT2 up to --mix-share of the epoch "
        "(ROOT2's windows in turn over the epochs, augmented as the recipe says)",
    )
    flags.add_split(mix, "ROOT2's splits (default: --split)", flag="--mix-split")
    mix.add_argument("--mix-cache", type=Path, metavar="CACHE", help="scan cache of ROOT2 (rafd prepare)")
    mix.add_argument(
        "--mix-share",
        type=float,
        default=0.5,
        metavar="FRACTION",
        help="share of each epoch's windows drawn from ROOT2, in (0, 1) (default %(default)s: as many as ROOT has)",
    )
    parser.add_argument("--max-steps-per-epoch", type=int, help="cap optimizer steps per epoch (smoke runs)")
    flags.add_workers(parser, None, "DataLoader workers per process (default: 4 on CUDA, 0 on CPU)")
    flags.add_threads(parser, None, "torch's CPU threads per process (default: CPUs / processes)")
    parser.add_argument("--log-every", type=int, default=20, help="optimizer steps between loss logs")
    parser.add_argument("--dist-timeout", type=float, default=30.0, help="process-group timeout in minutes")
    flags.add_quiet(parser)
    flags.deprecated(parser, "--data", "the positional ROOT", "data_option", type=Path, metavar="ROOT")
    flags.deprecated(parser, "--frames", "--window-frames", "frames", type=int, metavar="N")
    flags.deprecated(parser, "--num-workers", "--workers", "workers", type=int, metavar="N")
    flags.deprecated(parser, "--no-progress", "--quiet", "quiet", kind="store_true")
    return parser


def parse(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """The flags, old spellings moved to the new ones (ROOT from --data; --resume continues --out)."""
    parser = build_parser()
    argv, legacy_resume = flags.legacy_resume_path(sys.argv[1:] if argv is None else argv, parser.prog)
    args = parser.parse_args(argv)
    args.resume = legacy_resume or args.resume
    flags.resolve_data_root(parser, args)
    return args


def train_run(args: argparse.Namespace) -> TrainRun:
    """The flags as a TrainRun (one flag per field); repeated or comma-separated splits as one tuple."""
    renamed = {"num_workers": "workers", "progress": None, "resume": None}
    values = {
        f.name: getattr(args, renamed.get(f.name) or f.name)
        for f in dataclasses.fields(TrainRun)
        if f.name not in renamed or renamed[f.name]
    }
    values["split"] = flags.split_names(args.split)
    values["val_split"] = flags.split_names(args.val_split) if args.val_split else None
    values["mix_split"] = flags.split_names(args.mix_split) if args.mix_split else None
    values["freeze"] = tuple(args.freeze)
    values["progress"] = not args.quiet
    # --resume continues --out; the deprecated --resume PATH continues PATH
    values["resume"] = args.resume if isinstance(args.resume, Path) else (args.out if args.resume else None)
    return TrainRun(**values)


def main(argv: Sequence[str] | None = None) -> int:
    args = parse(argv)
    flags.apply_quiet(args)
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
