"""The synthetic benchmark's variants: each changes the benchmark's training run as the paper's ablation says."""

from __future__ import annotations

from pathlib import Path

from bench.accuracy import markdown_table
from bench.variants import VARIANTS
from rafd.train.run import TrainRun

BASE = TrainRun(data=Path("data"), split=("train",), out=Path("model.pt"), config="default", input_size=256)


def test_variants_map_to_the_papers_ablations() -> None:
    assert VARIANTS["single"].apply(BASE) == TrainRun(**{**BASE.__dict__, "frames": 1})
    assert VARIANTS["no_flow_sup"].apply(BASE).no_flow_supervision
    baseline = VARIANTS["baseline"].apply(BASE)
    assert baseline.no_enhancement and baseline.no_flow_supervision and baseline.no_flow_guidance
    frozen = VARIANTS["rafd4_from_single_frozen"]
    assert frozen.init == "single" and frozen.apply(BASE).freeze == ("encoder",)
    fresh_only = VARIANTS["rafd4_from_single_fresh_only"]
    assert fresh_only.init == "single" and fresh_only.apply(BASE).freeze == ("encoder", "head")
    flow4 = VARIANTS["rafd4_from_single_fresh_only_flow4"]  # the shipped recipe, only the flow stride differs
    assert flow4.init == "single"
    assert flow4.apply(BASE) == TrainRun(**{**fresh_only.apply(BASE).__dict__, "flow_stride": 4})
    legacy = VARIANTS["rafd4_legacy_targets"].apply(BASE)
    assert (legacy.box_encoding, legacy.heatmap_min_overlap, legacy.heatmap_min_radius) == ("as_labelled", 0.7, 1)


def test_variants_change_only_what_they_name() -> None:
    untouched = {"data", "split", "out", "config", "input_size", "seed", "epochs", "lr", "init", "resume"}
    for variant in VARIANTS.values():
        changed = variant.apply(BASE)
        assert all(getattr(changed, name) == getattr(BASE, name) for name in untouched), variant.name


def test_markdown_table_marks_missing_figures() -> None:
    table = markdown_table([{"variant": "rafd4", "description": "d", "mAP@0.3": 50.0, "epe_all": float("nan")}])
    assert "| rafd4 | d | 50.00 |" in table and "| - |" in table
