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
import typing
from collections.abc import Callable, Sequence
from functools import lru_cache
from pathlib import Path
from typing import Any

from rafd.cli import flags
from rafd.config import BOX_ENCODINGS, FREEZABLE
from rafd.train.run import TRAIN_CONFIG_NAMES, TrainRun

Group = argparse.ArgumentParser | argparse._ArgumentGroup
# Fields whose flag is a shared one (rafd.cli.flags: one meaning and help in every command), given the field's help
# where the shared flag takes one. Every other field becomes --FIELD-NAME, made by field_flag.
SHARED: dict[str, Callable[[Group, dataclasses.Field[Any]], object]] = {
    "data": lambda group, field: group.add_argument(
        "data", type=Path, metavar=field.metadata["metavar"], help=field.metadata["help"]
    ),
    "split": lambda group, field: flags.add_split(group, field.metadata["help"], required=True),
    "val_split": lambda group, field: flags.add_split(group, field.metadata["help"], flag="--val-split"),
    "mix_split": lambda group, field: flags.add_split(group, field.metadata["help"], flag="--mix-split"),
    "out": lambda group, field: flags.add_out(group, field.metadata["metavar"], field.metadata["help"], required=True),
    "frames": lambda group, field: flags.add_window_frames(group, choices=(1, 2, 4)),
    "num_workers": lambda group, field: flags.add_workers(group, None, field.metadata["help"]),
    "threads": lambda group, field: flags.add_threads(group, None, field.metadata["help"]),
    "device": lambda group, field: flags.add_device(group),
    "progress": lambda group, field: flags.add_quiet(group),
    "resume": lambda group, field: flags.add_resume(group, field.metadata["help"]),
    "warm_up_windows": lambda group, field: flags.add_warm_up_windows(group),
}


def build_parser() -> argparse.ArgumentParser:
    """One flag per TrainRun field, in the field's group, with the field's help and default, as `rafd serve`'s flags
    are made from the service's Settings: a field added to TrainRun is a flag at once."""
    parser = argparse.ArgumentParser(
        prog=flags.prog("train"), description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    groups: dict[str | None, Group] = {None: parser}
    adders = {**SHARED, "config": add_config}
    for field in dataclasses.fields(TrainRun):
        title = field.metadata["group"]
        if title not in groups:
            groups[title] = parser.add_argument_group(title)
        adders.get(field.name, field_flag)(groups[title], field)
    return parser


def add_config(group: Group, field: dataclasses.Field[Any]) -> None:
    from rafd.train.recipes import RECIPES

    recipes = "; ".join(f"{r.name}: {r.description}" for r in RECIPES.values())
    flags.add_config(group, RECIPES, str(field.default), f"{field.metadata['help']}; {recipes}")


@lru_cache(maxsize=1)
def choices() -> dict[str, Sequence[str]]:
    """The values a field may take, from the code that checks them."""
    from rafd.model.precision import PRECISIONS
    from rafd.train.trainer import OPTIMIZERS, SCHEDULES

    return {
        "optimizer": OPTIMIZERS,
        "lr_schedule": SCHEDULES,
        "precision": PRECISIONS,
        "box_encoding": BOX_ENCODINGS,
        "propagation_norm": ("post", "pre"),
        "freeze": FREEZABLE,
    }


def field_flag(group: Group, field: dataclasses.Field[Any]) -> None:
    """--FIELD-NAME from the field's type: a flag for a bool (--x / --no-x for a bool that may be None), one or more
    values for a tuple, else one value of the type."""
    kind = field_types()[field.name]
    options: dict[str, Any] = {"dest": field.name, "default": field.default, "help": help_text(field)}
    if kind is bool:
        options["action"] = "store_true" if field.default is False else argparse.BooleanOptionalAction
    elif typing.get_origin(kind) is tuple:
        options.update(nargs="+", type=typing.get_args(kind)[0])
    else:
        options["type"] = kind
    if field.name in choices():
        options["choices"] = choices()[field.name]
    if field.metadata["metavar"]:
        options["metavar"] = field.metadata["metavar"]
        if "choices" in options:  # the metavar hides them in the usage line
            options["help"] += f" (choices: {', '.join(options['choices'])})"
    group.add_argument("--" + field.name.replace("_", "-"), **options)


def help_text(field: dataclasses.Field[Any]) -> str:
    """The field's help and its default: its own, else (None) the training default every recipe keeps."""
    default = field.default if field.default is not None else recipe_default(field.name)
    unset = default is None or isinstance(default, bool) or default == ()  # nothing to show: off, none
    shown = "" if unset else f" (default: {default})"
    return f"{field.metadata['help']}{shown}".replace("%", "%%")


def recipe_default(name: str) -> Any:
    """The value of the TrainConfig field `name` overrides when every recipe has the same one, else None."""
    from rafd.train.recipes import RECIPES

    config_name = TRAIN_CONFIG_NAMES.get(name, name)
    values = {getattr(recipe.train, config_name, None) for recipe in RECIPES.values()}
    return values.pop() if len(values) == 1 else None


@lru_cache(maxsize=1)
def field_types() -> dict[str, Any]:
    """Field name -> its type, `X | None` read as X (None is the flag not given)."""
    found = {}
    for name, hint in typing.get_type_hints(TrainRun).items():
        found[name] = flags.without_none(hint)
    return found


def parse(argv: Sequence[str] | None = None) -> argparse.Namespace:
    return build_parser().parse_args(argv)


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
    values["resume"] = args.out if args.resume else None  # --resume continues --out
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
