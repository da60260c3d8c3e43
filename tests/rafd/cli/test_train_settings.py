"""rafd train's command line: a recipe, then KEY=VALUE settings of the one run config (every field settable, text
parsed by the field's type, mistakes refused by name), and the flags that say where (data, checkpoint, validation and
mixed-in roots)."""

from __future__ import annotations

from pathlib import Path

import pytest

from rafd.cli.train import main, parse, train_run
from rafd.config_tree import dotted_items
from rafd.train.recipes import RECIPES, recipe_config
from rafd.train.run import DataSource

BASE = ["ROOT", "--split", "train", "--out", "m.pt"]


def text(value: object) -> str:
    return ",".join(str(v) for v in value) if isinstance(value, tuple) else "none" if value is None else str(value)


@pytest.mark.parametrize("recipe", sorted(RECIPES))
def test_a_run_without_settings_trains_the_recipe_as_it_is(recipe: str) -> None:
    run = train_run(parse([*BASE, "--config", recipe]))
    assert run.config == recipe_config(recipe) and run.recipe == recipe
    assert run.data == DataSource(Path("ROOT"), ("train",)) and run.val is None and run.mix is None


@pytest.mark.parametrize("recipe", sorted(RECIPES))
def test_every_field_is_settable_by_its_dotted_key(recipe: str) -> None:
    """Each field set to its own value as text gives the same config: every key parses, none is missing."""
    config = recipe_config(recipe)
    settings = [f"{key}={text(value)}" for key, value in dotted_items(config)]
    assert len(settings) > 70
    assert train_run(parse([*BASE, "--config", recipe, *settings])).config == config


def test_settings_reach_their_fields_whatever_their_place_among_the_flags() -> None:
    argv = ["model.flow.local_radius=1", "ROOT", "--split", "a,b", "model.flow.channels=8", "--out", "m.pt"]
    run = train_run(parse([*argv, "--config", "cpu", "train.lr=1e-3", "train.freeze=encoder,head"]))
    assert (run.config.model.flow.local_radius, run.config.model.flow.channels) == (1, 8)
    assert run.config.train.lr == 1e-3 and run.config.train.freeze == ("encoder", "head")
    assert run.data.splits == ("a", "b") and run.config.model.propagation.mode == "joint"  # the rest: cpu's


def test_typed_values_none_and_booleans() -> None:
    run = train_run(parse([*BASE, "train.micro_batch_size=2", "train.threads=none", "data.warm_up_windows=yes"]))
    assert run.config.train.micro_batch_size == 2 and run.config.train.threads is None
    assert run.config.data.warm_up_windows is True
    run = train_run(parse([*BASE, "data.augment.gain_range=0.5,2", "model.backbone.blocks=1,1,1"]))
    assert run.config.data.augment.gain_range == (0.5, 2.0)


def test_the_run_augmentation_changes_roots_own_and_leaves_the_mixed_in_roots() -> None:
    run = train_run(parse([*BASE, "--config", "default", "--mix-data", "SIM", "data.augment.shift_max_m=20"]))
    assert run.config.data.augment.shift_max_m == 20.0 and run.config.data.mix_augment.shift_max_m == 65.0
    assert run.mix == DataSource(Path("SIM"), ("train",))


def test_validation_reads_root_and_its_cache_unless_another_root_is_named() -> None:
    run = train_run(parse([*BASE, "--cache", "C", "--val-split", "val"]))
    assert run.val == DataSource(Path("ROOT"), ("val",), Path("C"))
    run = train_run(parse([*BASE, "--cache", "C", "--val-data", "V"]))
    assert run.val == DataSource(Path("V"), ("test",), None)


def test_show_config_prints_every_setting_without_a_root(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--config", "cpu", "--show-config", "model.flow.local_radius=2"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert "model.flow.local_radius=2" in lines and "train.lr_schedule=cosine" in lines
    assert len(lines) == len(list(dotted_items(recipe_config("cpu"))))


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        ([*BASE, "train.lr=fast"], "train.lr takes float"),
        ([*BASE, "model.flow.radius=2"], "did you mean model.flow.local_radius"),
        ([*BASE, "model.flow=2"], "model.flow is a group"),
        ([*BASE, "model.num_frames=3"], "num_frames must be one of"),
        ([*BASE, "train.freeze=wings"], "not parts of the network"),
        (["--split", "train", "--out", "m.pt"], "required: ROOT"),
    ],
)
def test_a_setting_that_cannot_hold_is_refused_by_name(argv: list[str], message: str, capsys) -> None:
    with pytest.raises(SystemExit):
        parse(argv)
    assert message in capsys.readouterr().err
