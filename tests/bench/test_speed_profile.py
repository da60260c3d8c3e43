"""rafd bench speed --profile (bench.speed_profile): the by-module table of the exported streaming step, on small
random-weight networks of both propagations (the default's chain, the cpu recipe's joint block)."""

from __future__ import annotations

import dataclasses
import json
import re
from collections import Counter
from pathlib import Path

import onnx
import pytest
import torch

from bench.speed_cli import main
from bench.speed_profile import (
    OUTSIDE,
    REPEAT_SUFFIX,
    format_profiles,
    group_rows,
    module_tree,
    node_scopes,
    open_session,
    profile_steps,
    row_of,
    scope_of,
    step_feeds,
    step_onnx,
    timed_node_ms,
)
from rafd import RaFDConfig, build_model, save_checkpoint
from rafd.train.recipes import recipe_model

TOP_LEVEL = {"encoder", "flow_encode", "flow_match", "propagation", "head"}


def small_config(propagation: str) -> RaFDConfig:
    """The tiny network at 64 px: the default's chain propagation, or the cpu recipe's reshaping (conv enhancement,
    local cost volume, one joint propagation block)."""
    cfg = RaFDConfig.tiny(input_size=64)
    if propagation == "joint":
        cfg = cfg.replace(
            enhance=dataclasses.replace(cfg.enhance, kind="conv", window=0),
            flow=dataclasses.replace(cfg.flow, num_cross_blocks=0, local_radius=3, channels=8),
            propagation=dataclasses.replace(cfg.propagation, mode="joint", num_blocks=1, num_points=2),
        )
    return cfg


@pytest.fixture(scope="module")
def checkpoints(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    work = tmp_path_factory.mktemp("profile")
    paths = {}
    for kind in ("chain", "joint"):
        torch.manual_seed(0)
        cfg = small_config(kind)
        paths[kind] = work / f"{kind}.pt"
        save_checkpoint(paths[kind], build_model(cfg).eval(), cfg)
    return paths


@pytest.fixture(scope="module")
def steps(checkpoints: dict[str, Path]) -> dict[str, Path]:
    return {kind: step_onnx(path, path.parent) for kind, path in checkpoints.items()}


def profiled_nodes(path: Path, tmp: Path) -> tuple[dict[str, float], dict[str, tuple[str, ...]], dict]:
    """node -> ms per step, node -> module path, the module tree of one graph profiled over 2 steps."""
    session = open_session(path, 1, tmp)
    feeds = step_feeds(session)
    for _ in range(3):
        session.run(None, feeds)
    node_ms = timed_node_ms(json.loads(Path(session.end_profiling()).read_text()), 2)
    tree = module_tree(onnx.load(str(path)).graph)
    return node_ms, node_scopes(onnx.load(str(tmp / "optimised.onnx")).graph, tree), tree


@pytest.mark.parametrize("kind", ["chain", "joint"])
@pytest.mark.parametrize("depth", [1, 2, 3])
def test_every_profiled_node_is_in_exactly_one_row_and_the_rows_sum_to_the_total(
    steps: dict[str, Path], tmp_path: Path, kind: str, depth: int
):
    node_ms, scopes, tree = profiled_nodes(steps[kind], tmp_path)
    rows = group_rows(node_ms, scopes, tree, depth)
    modules = [row.module for row in rows]
    assert len(modules) == len(set(modules))
    charged = Counter(row_of(node, scopes, tree, depth) for node in node_ms)
    assert charged == {row.module: row.nodes for row in rows}  # each node in one row, and every row's are its own
    assert sum(row.nodes for row in rows) == len(node_ms)
    assert sum(row.ms for row in rows) == pytest.approx(sum(node_ms.values()), rel=1e-9)
    assert all(module.count("/") < depth for module in modules)


@pytest.mark.parametrize("kind", ["chain", "joint"])
def test_the_known_modules_appear_and_little_is_outside_them(steps: dict[str, Path], kind: str):
    (top,) = profile_steps({kind: steps[kind]}, repeats=2, depth=1)
    assert top.total_ms == pytest.approx(sum(row.ms for row in top.rows))
    assert top.wall_ms > 0
    assert TOP_LEVEL <= {row.module for row in top.rows} <= TOP_LEVEL | {OUTSIDE}
    order = ["encoder", "flow_encode", "flow_match", "propagation", "head"]  # the step's
    assert [row.module for row in top.rows if row.module != OUTSIDE] == order
    # outside any module: only the step's own cache bookkeeping (RaFD.step); every matrix operation is in one
    graph = onnx.load(str(steps[kind])).graph
    assert not [
        n.name for n in graph.node if n.op_type in ("Conv", "MatMul", "Gemm", "GridSample") and n.name.count("/") < 2
    ]
    (second,) = profile_steps({kind: steps[kind]}, repeats=2, depth=2)
    modules = {row.module for row in second.rows}
    assert {"encoder/backbone", "encoder/neck", "encoder/enhancement", "flow_encode/encoder", "flow_match"} <= modules
    assert {"propagation/layers.0", "head/heatmap", "head/decoder"} <= modules
    assert ("propagation/layers.1" in modules) == (kind == "chain")  # 2 chained blocks against 1 joint block


def test_names_are_charged_to_the_longest_module_path_they_start_with():
    tree = {(): 0, ("head",): 1, ("propagation",): 2, ("propagation", "layers.0"): 3}
    assert scope_of("/head/Gather_1/GatherSliceToSplitFusion", tree) == ("head",)  # onnxruntime's fused name
    assert scope_of("/propagation_1/layers.0_2/Mul_3", tree) == ("propagation", "layers.0")  # repeated calls
    assert scope_of("/propagation/layers.0/Add_output_0", tree) == ("propagation", "layers.0")  # a tensor
    assert scope_of("/Concat_2", tree) == ()
    assert scope_of("Gelu_token_3", tree) is None and scope_of("heatmap", tree) is None


def test_nodes_onnxruntime_inserted_are_charged_by_their_tensors_or_neighbours():
    from onnx import helper

    nodes = [
        helper.make_node("Relu", ["x"], ["/head/heatmap/Relu_output_0"], name="/head/heatmap/Relu"),
        helper.make_node("ReorderInput", ["/head/heatmap/Relu_output_0"], ["token_1"], name="ReorderInput"),
        helper.make_node("Conv", ["token_1"], ["token_2"], name="heatmap_nchwc"),
        helper.make_node("ReorderOutput", ["token_2"], ["heatmap"], name="ReorderOutput_token_3"),
        helper.make_node("Gelu", ["y"], ["/flow/match/Mul_1_output_0"], name="Gelu"),
    ]
    graph = helper.make_graph(nodes, "g", [], [])
    tree = {(): 0, ("head",): 0, ("head", "heatmap"): 0, ("flow",): 4, ("flow", "match"): 4}
    scopes = node_scopes(graph, tree)
    assert scopes == {
        "/head/heatmap/Relu": ("head", "heatmap"),
        "ReorderInput": ("head", "heatmap"),  # by the tensor it reads
        "heatmap_nchwc": ("head", "heatmap"),  # by its producer
        "ReorderOutput_token_3": ("head", "heatmap"),
        "Gelu": ("flow", "match"),  # by the tensor it writes
    }


@pytest.mark.parametrize("name", ["default", "cpu", "tiny", "paper"])
def test_no_module_is_named_like_the_exporters_repeat_suffix(name: str):
    """scope_of strips "_1", "_2" from every part: the exporter's suffix of a module called again."""
    model = build_model(recipe_model(name))
    atoms = {atom for qualified, _ in model.named_modules() for atom in qualified.split(".")}
    assert not [atom for atom in atoms if REPEAT_SUFFIX.search(atom) and not atom.isdigit()]


def test_two_steps_side_by_side_share_the_rows_and_give_their_ratio(steps: dict[str, Path]):
    profiles = profile_steps({"chain": steps["chain"], "joint": steps["joint"]}, repeats=2, depth=2)
    table = format_profiles(profiles, 2, "test machine", profiler_us=5.0)
    assert "| module | chain ms | % | nodes | joint ms | % | nodes | joint / chain |" in table
    assert re.search(
        r"\| propagation/layers\.1 \| [0-9.]+ \| [0-9.]+ \| \d+ \| - \| - \| - \| - \|", table
    )  # chain only
    lines = table.splitlines()
    first = [
        next(n for n, line in enumerate(lines) if line.startswith(f"| {m}")) for m in ("encoder/", "flow_match", "head")
    ]
    assert first == sorted(first)  # the module tree's order
    assert lines[-3].startswith("| wall median, no profiler |") and "a chain of 500 scalar Adds" in lines[-1]


def test_the_cli_profiles_a_checkpoint_and_writes_json(
    checkpoints: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
):
    out = tmp_path / "profile.json"
    assert main([str(checkpoints["chain"]), "--profile", "--repeats", "2", "--json", str(out), "--quiet"]) == 0
    table = capsys.readouterr().out
    assert "| module | chain.pt ms | % | nodes |" in table
    for row in (
        "encoder/backbone",
        "flow_match (own ops)",
        "propagation/layers.0",
        "head/decoder",
        "**TOTAL** (sum of the rows)",
    ):
        assert f"| {row} |" in table
    assert re.search(r"\| wall median, no profiler \| [0-9.]+ \| TOTAL = [0-9.]+% of it \|", table)
    assert "µs per node" in table
    figures = json.loads(out.read_text())["profile"]
    (chain,) = figures["configs"].values()
    assert sum(row["ms"] for row in chain["rows"]) == pytest.approx(chain["total_ms"])
    assert chain["wall_ms"] > 0 and figures["depth"] == 2 and figures["threads"] == 1


def test_the_cli_refuses_an_unknown_recipe(capsys: pytest.CaptureFixture[str]):
    assert main(["--profile-config", "default,huge"]) == 2
    assert "huge" in capsys.readouterr().err
