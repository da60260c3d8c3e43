"""The synthetic benchmark's variants: each changes the benchmark's training run as the paper's ablation says, and
nothing else."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from bench.accuracy import markdown_table
from bench.variants import VARIANTS
from rafd.config_tree import dotted_items
from rafd.train.recipes import recipe_config
from rafd.train.run import DataSource, TrainRun

BASE = TrainRun(
    config=recipe_config("default").overridden({"model.input_size": 256}),
    data=DataSource(Path("data"), ("train",)),
    out=Path("model.pt"),
    recipe="default",
)


def changes(name: str) -> dict[str, object]:
    """The settings a variant changes in the benchmark's run config."""
    before = dict(dotted_items(BASE.config))
    return {k: v for k, v in dotted_items(VARIANTS[name].apply(BASE).config) if v != before[k]}


def test_variants_map_to_the_papers_ablations() -> None:
    assert changes("single") == {"model.num_frames": 1}
    assert changes("no_flow_sup") == {"loss.flow_weight": 0.0}
    assert changes("baseline") == {
        "model.enhance.enabled": False,
        "model.propagation.flow_guided": False,
        "loss.flow_weight": 0.0,
    }
    frozen = VARIANTS["rafd4_from_single_frozen"]
    assert frozen.init == "single" and changes(frozen.name) == {"train.freeze": ("encoder",)}
    fresh_only = VARIANTS["rafd4_from_single_fresh_only"]
    assert fresh_only.init == "single" and changes(fresh_only.name) == {"train.freeze": ("encoder", "head")}
    flow4 = VARIANTS["rafd4_from_single_fresh_only_flow4"]  # the shipped recipe, only the flow stride differs
    assert flow4.init == "single"
    assert changes(flow4.name) == {"train.freeze": ("encoder", "head"), "model.flow.stride": 4}
    assert changes("rafd4_legacy_targets") == {
        "model.head.box_encoding": "as_labelled",
        "model.targets.heatmap_min_overlap": 0.7,
        "model.targets.heatmap_min_radius": 1,
    }
    assert changes("rafd4") == {}


def test_variants_change_only_the_config() -> None:
    for variant in VARIANTS.values():
        changed = variant.apply(BASE)
        assert dataclasses.replace(changed, config=BASE.config) == BASE, variant.name


def test_markdown_table_marks_missing_figures() -> None:
    table = markdown_table([{"variant": "rafd4", "description": "d", "mAP@0.3": 50.0, "epe_all": float("nan")}])
    assert "| rafd4 | d | 50.00 |" in table and "| - |" in table
