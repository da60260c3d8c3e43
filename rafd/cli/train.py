"""rafd train: train RaFD on a RADIATE-layout data root (one process, or several under torchrun).

The run config (rafd.train.config) is one tree: `model.*` the network, `data.*` how windows are drawn and augmented,
`loss.*` the loss weights, `train.*` the optimisation and how it runs. `--config NAME` starts from a recipe
(rafd.train.recipes) and every KEY=VALUE after it sets one field by its dotted key; `--show-config` prints them all.
The flags say where: the data, the checkpoint, where the weights start, the validation and mixed-in roots. The
checkpoint records the recipe and the whole config. Prepare the data once first: `rafd odometry ROOT` (ego poses) and
`rafd prepare ROOT --out CACHE` (decoded crops; then pass --cache CACHE). `train.batch_size` is the global batch
(over all processes), as in the paper. An interrupted run goes on with the same command and `--resume`.
"""

from __future__ import annotations

import argparse
import json
import logging
import re
import sys
from collections.abc import Sequence
from pathlib import Path

from rafd.cli import flags
from rafd.config_tree import dotted_items, parse_overrides
from rafd.train.recipes import RECIPES, recipe_config
from rafd.train.run import DataSource, TrainRun

# KEY=VALUE: a dotted key of the run config (a data root is a positional that is not one)
SETTING = re.compile(r"^[a-z_][a-z0-9_]*(\.[a-z_][a-z0-9_]*)+=")

EXAMPLES = """settings (KEY=VALUE, any field of the run config; `--show-config` lists them with their values):
  model.num_frames=1                      a single-frame model (frames per window: 1, 2 or 4)
  model.input_size=256                    the model's input crop in pixels
  model.flow.local_radius=2 model.flow.channels=8
  model.enhance.enabled=false             ablation: no window self-attention
  model.propagation.flow_guided=false     ablation: vanilla deformable attention
  loss.flow_weight=0                      ablation: no flow supervision
  train.lr=1e-3 train.epochs=20 train.batch_size=8 train.precision=bf16 train.device=cpu train.threads=2
  train.freeze=encoder,head               parts that do not train (with --init)
  data.augment.enabled=false              no augmentation; data.augment.shift_max_m=20: crops up to 20 m away
"""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=flags.prog("train"),
        description=__doc__,
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "arguments",
        nargs="*",
        metavar="ROOT|KEY=VALUE",
        help="the data root holding sequence folders, then the settings of the run config",
    )
    flags.add_split(parser, "the splits to train on")
    flags.add_out(parser, "CKPT", "checkpoint to write (+ .optim.pt, .history.json)")
    recipes = "; ".join(f"{r.name}: {r.description}" for r in RECIPES.values())
    flags.add_config(parser, RECIPES, "tiny", f"the recipe the config starts from; {recipes}")
    parser.add_argument("--cache", type=Path, help="scan cache of ROOT written by rafd prepare (default: the PNGs)")
    flags.add_resume(parser, "the same command again after an interruption (the config must be the run's)")
    parser.add_argument(
        "--init",
        type=Path,
        metavar="CKPT",
        help="start from this checkpoint's weights where names and shapes match (e.g. a single-frame model under a "
        "4-frame run); optimizer, schedule and epochs start fresh",
    )
    parser.add_argument(
        "--teacher",
        type=Path,
        metavar="CKPT",
        help="distil this trained model: its heatmap is a soft target beside the labels (weight loss.distill_weight), "
        "e.g. a wide model teaching a narrower network; it must read the same input and see at least as many frames",
    )
    parser.add_argument(
        "--show-config", action="store_true", help="print the config's every KEY=VALUE (recipe and settings) and exit"
    )
    flags.add_quiet(parser)
    validation = parser.add_argument_group("validation every train.val_every epochs (default: none)")
    validation.add_argument("--val-data", type=Path, metavar="ROOT", help="validation data root (default: ROOT)")
    flags.add_split(validation, "validation splits (default: test)", flag="--val-split")
    validation.add_argument(
        "--val-cache", type=Path, metavar="CACHE", help="scan cache of the validation root (default: --cache)"
    )
    mix = parser.add_argument_group(
        "a second data root mixed into every epoch (e.g. simulated drives replayed while fine-tuning on real scans)"
    )
    mix.add_argument(
        "--mix-data",
        type=Path,
        metavar="ROOT2",
        help="every epoch holds each window of ROOT once plus windows of ROOT2 up to data.mix_share of the epoch "
        "(ROOT2's windows in turn over the epochs, augmented as data.mix_augment says: the recipe's)",
    )
    flags.add_split(mix, "ROOT2's splits (default: --split)", flag="--mix-split")
    mix.add_argument("--mix-cache", type=Path, metavar="CACHE", help="scan cache of ROOT2 (rafd prepare)")
    return parser


def parse(argv: Sequence[str] | None = None) -> argparse.Namespace:
    """The flags; args.root the data root (None with --show-config alone) and args.settings {key: text}."""
    parser = build_parser()
    args = parser.parse_intermixed_args(argv)
    settings = [a for a in args.arguments if SETTING.match(a)]
    roots = [a for a in args.arguments if not SETTING.match(a)]
    if len(roots) > 1:
        parser.error(f"one data root, got {roots} (a setting is KEY=VALUE with a dotted key, e.g. train.lr=1e-3)")
    args.root = Path(roots[0]) if roots else None
    try:
        args.settings = parse_overrides(settings)
        args.run_config = recipe_config(args.config).overridden(args.settings)
    except ValueError as error:
        parser.error(str(error))
    if not args.show_config:
        given = {"ROOT": args.root, "--split": args.split, "--out": args.out}
        missing = [what for what, value in given.items() if not value]
        if missing:
            parser.error(f"the following arguments are required: {', '.join(missing)}")
        if args.mix_data is None and (args.mix_split or args.mix_cache):
            parser.error("--mix-split and --mix-cache describe --mix-data ROOT2: give it too")
    return args


def train_run(args: argparse.Namespace) -> TrainRun:
    """The parsed command line as a TrainRun: repeated or comma-separated splits as one tuple; validation on ROOT
    (and its cache) unless --val-data names another root."""
    splits = flags.split_names(args.split)
    val = None
    if args.val_data is not None or args.val_split:
        val_root = args.val_data if args.val_data is not None else args.root
        val_cache = args.val_cache if args.val_cache is not None else (args.cache if val_root == args.root else None)
        val = DataSource(val_root, flags.split_names(args.val_split) or ("test",), val_cache)
    mix = None
    if args.mix_data is not None:
        mix = DataSource(args.mix_data, flags.split_names(args.mix_split) or splits, args.mix_cache)
    return TrainRun(
        config=args.run_config,
        data=DataSource(args.root, splits, args.cache),
        out=args.out,
        recipe=args.config,
        resume=args.resume,
        init=args.init,
        teacher=args.teacher,
        val=val,
        mix=mix,
    )


def main(argv: Sequence[str] | None = None) -> int:
    args = parse(argv)
    flags.apply_quiet(args)
    if args.show_config:
        print("\n".join(f"{key}={_text(value)}" for key, value in dotted_items(args.run_config)))
        return 0
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
        print(f"{flags.prog('train')}: error: {error}", file=sys.stderr)
        return 2
    if rank == 0:
        last = {k: v for k, v in history[-1].items() if k != "curve"} if history else None
        print(json.dumps({"checkpoint": str(run.out), "last_epoch": last}, indent=2))
    return 0


def _text(value: object) -> str:
    """A value as a setting is written: a tuple comma-separated, None as none, a bool as true / false."""
    if isinstance(value, tuple):
        return ",".join(str(v) for v in value)
    if value is None:
        return "none"
    if isinstance(value, bool):
        return str(value).lower()
    return str(value)


if __name__ == "__main__":
    sys.exit(main())
