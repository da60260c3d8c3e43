"""rafd train's flags are made from TrainRun's fields: one flag per field with the field's help, and every training
default written once (TrainConfig's, or the field's own): a run without flags is the recipe as it is."""

from __future__ import annotations

import argparse
import dataclasses

import pytest

from rafd.cli.train import SHARED, build_parser, parse, train_run
from rafd.train.recipes import RECIPES
from rafd.train.run import TrainRun, train_config
from rafd.train.trainer import TrainConfig

BASE = ["ROOT", "--split", "train", "--out", "m.pt"]
# the fields whose flag is a shared one with a help of its own (rafd.cli.flags), and their flag's dest
FIXED_HELP = {"frames": "frames", "device": "device", "progress": "quiet", "warm_up_windows": "warm_up_windows"}


def actions() -> dict[str, argparse.Action]:
    """dest -> its flag (the first: a deprecated spelling of the same dest comes after it)."""
    found: dict[str, argparse.Action] = {}
    for action in build_parser()._actions:
        found.setdefault(action.dest, action)
    return found


@pytest.mark.parametrize("field", dataclasses.fields(TrainRun), ids=lambda f: f.name)
def test_every_field_is_a_flag_with_the_fields_help(field: dataclasses.Field) -> None:
    assert field.metadata["help"], f"TrainRun.{field.name} has no help"
    dest = {"num_workers": "workers", **FIXED_HELP}.get(field.name, field.name)
    action = actions()[dest]
    if field.name not in FIXED_HELP:
        assert field.metadata["help"] in action.help.replace("%%", "%"), field.name


@pytest.mark.parametrize("recipe", sorted(RECIPES))
def test_a_run_without_flags_trains_the_recipe_as_it_is(recipe: str) -> None:
    run = train_run(parse([*BASE, "--config", recipe]))
    assert train_config(run, RECIPES[recipe].train) == RECIPES[recipe].train
    assert train_config(TrainRun(data=run.data, split=run.split, out=run.out), RECIPES[recipe].train) == (
        RECIPES[recipe].train
    )


def test_the_training_defaults_are_trainconfigs_shown_in_the_help() -> None:
    """The flags' own defaults are 'not given' (None): the value and the help's default come from TrainConfig."""
    found = actions()
    for name, config_name in (("grad_clip", "grad_clip"), ("log_every", "log_every"), ("seed", "seed")):
        assert found[name].default is None
        assert f"(default: {getattr(TrainConfig(), config_name)})" in found[name].help
    assert found["dist_timeout"].default is None
    assert f"(default: {TrainConfig().dist_timeout_minutes})" in found["dist_timeout"].help
    assert found["mix_share"].default == TrainRun.__dataclass_fields__["mix_share"].default


def test_a_flag_given_reaches_the_train_config() -> None:
    argv = [*BASE, "--grad-clip", "1.5", "--log-every", "3", "--dist-timeout", "5", "--seed", "7", "--val-every", "0"]
    cfg = train_config(train_run(parse([*argv, "--precision", "bf16", "--quiet"])), RECIPES["tiny"].train)
    assert (cfg.grad_clip, cfg.log_every, cfg.dist_timeout_minutes, cfg.seed, cfg.val_every) == (1.5, 3, 5.0, 7, 0)
    assert (cfg.precision, cfg.progress) == ("bf16", False)


def test_the_shared_flags_cover_only_fields() -> None:
    assert set(SHARED) <= {f.name for f in dataclasses.fields(TrainRun)}
