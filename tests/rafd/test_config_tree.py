"""rafd.config_tree: a config's dict round trip refuses unknown and missing keys; dotted settings parse text by the
field's type, take Python values as they are, rebuild the tree once (its checks judge the whole result) and refuse
a key that is no field by naming the closest one."""

from __future__ import annotations

from pathlib import Path

import pytest

from rafd.config import RaFDConfig
from rafd.config_tree import dotted_items, from_dict, overridden, parse, parse_overrides, to_dict
from rafd.train.config import RunConfig


def test_the_dict_round_trip_is_exact_and_strict() -> None:
    config = RunConfig(model=RaFDConfig.tiny())
    assert from_dict(RunConfig, to_dict(config)) == config
    data = to_dict(config)
    data["train"]["bogus"] = 1
    with pytest.raises(ValueError, match=r"unknown fields \['bogus'\]"):
        from_dict(RunConfig, data)
    data = to_dict(config)
    del data["loss"]["flow_weight"]
    with pytest.raises(ValueError, match=r"missing fields \['flow_weight'\]"):
        from_dict(RunConfig, data)


def test_settings_change_the_fields_they_name_and_nothing_else() -> None:
    base = RunConfig()
    changed = overridden(base, {"model.flow.local_radius": "2", "train.lr": 1e-3, "train.freeze": "encoder,head"})
    assert (changed.model.flow.local_radius, changed.train.lr, changed.train.freeze) == (2, 1e-3, ("encoder", "head"))
    before, after = dict(dotted_items(base)), dict(dotted_items(changed))
    assert {k for k in before if before[k] != after[k]} == {"model.flow.local_radius", "train.lr", "train.freeze"}


def test_the_tree_is_checked_once_with_every_setting() -> None:
    """Blocks and channels of the backbone must have one length: each alone would be refused, both together hold."""
    base = RaFDConfig()
    with pytest.raises(ValueError, match="same length"):
        overridden(base, {"backbone.blocks": "1,1,1"})
    tiny = overridden(base, {"backbone.blocks": "1,1,1", "backbone.channels": "16,32,64"})
    assert tiny.backbone.channels == (16, 32, 64)


@pytest.mark.parametrize(
    ("kind", "text", "value"),
    [
        (bool, "true", True),
        (bool, "Off", False),
        (int | None, "none", None),
        (int | None, "3", 3),
        (float, "1e-3", 1e-3),
        (tuple[int, ...], "", ()),
        (tuple[str, ...], "encoder, head", ("encoder", "head")),
        (tuple[float, float], "0.5,2", (0.5, 2.0)),
        (Path | None, "runs/a.pt", Path("runs/a.pt")),
    ],
)
def test_text_is_parsed_by_the_fields_type(kind: object, text: str, value: object) -> None:
    assert parse(kind, text) == value


@pytest.mark.parametrize(
    ("kind", "text", "message"),
    [(bool, "maybe", "true or false"), (int, "2.5", "takes int"), (tuple[float, float], "1", "2 comma-separated")],
)
def test_text_a_field_cannot_take_is_refused(kind: object, text: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        parse(kind, text)


def test_unknown_keys_name_the_closest_setting() -> None:
    with pytest.raises(ValueError, match="did you mean train.lr_schedule"):
        overridden(RunConfig(), {"train.lr_schedul": "cosine"})
    with pytest.raises(ValueError, match="is no setting"):
        overridden(RunConfig(), {"nothing.here": "1"})
    with pytest.raises(ValueError, match="group of settings"):
        overridden(RunConfig(), {"data.augment": "1"})


def test_settings_are_key_equals_value() -> None:
    assert parse_overrides(["a.b=1", "c.d=x=y", "a.b=2"]) == {"a.b": "2", "c.d": "x=y"}
    with pytest.raises(ValueError, match="KEY=VALUE"):
        parse_overrides(["a.b"])
