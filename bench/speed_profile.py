"""`rafd bench speed --profile`: where a streaming step's time goes, module by module.

onnxruntime's own profiler (SessionOptions.enable_profiling) times every node of the step graph it runs (fp32, one
intra-op thread, sequential execution, the service's graph optimisations), over `repeats` steps after a warm-up;
each node is charged to the module of the network it came from, and the table gives the mean time per step of
each module, its node count, and a TOTAL (the sum of the rows) beside the median wall time of the same step run
without the profiler (interleaved with the profiled steps), so a reader sees how much of the step the rows cover.
The profiler's own bookkeeping lands inside each node's time, so the TOTAL can exceed the wall time: the run also
measures that cost per node (profiler_cost_us) and prints it under the table.

Node -> module: the TorchScript ONNX exporter names a node after the modules whose __call__ was on the stack when it
was traced ("/encoder/backbone/stages.0/stages.0.0/conv1/Conv"; a module called again gets "_1", "_2" appended,
which is stripped here: RaFD has no module named like that, tests/bench/test_speed_profile.py checks it). The
step graph (export.step) calls every part of the network through a module for that. onnxruntime renames what it
fuses or inserts (SkipLayerNormalization, Gelu, Reorder*, gemm reshapes), so a node without an exporter name is
charged by the tensors it writes (which keep the exporter's names), else by those it reads, else by its neighbours
in the optimised graph; what has no scope at all is "outside any module" (the step's own glue: relative poses,
concatenations of the caches).
"""

from __future__ import annotations

import bisect
import json
import logging
import re
import tempfile
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger("bench")

OUTSIDE = "outside any module"
PROFILE_THREADS = 1  # one thread: a node's time is its own work, not a share of a pool spinning between nodes
PROFILE_WARMUP = 3  # untimed steps first: the first runs allocate the arena and pack the weights
KERNEL = "_kernel_time"  # onnxruntime's profiler: one "Node" event "<node name>_kernel_time" per node run
CHAIN_NODES = 500  # profiler_cost_us's graph
REPEAT_SUFFIX = re.compile(r"_\d+$")  # the exporter's suffix of a module's second, third, ... call


@dataclass
class ProfileRow:
    module: str  # scope path to the profile's depth ("encoder/backbone"), or OUTSIDE
    ms: float  # ms per step of its nodes (the mean over the middle half of the profiled steps, timed_node_ms)
    nodes: int  # nodes of the optimised graph onnxruntime ran


@dataclass
class StepProfile:
    name: str  # the config or checkpoint profiled
    rows: list[ProfileRow]  # in the order of the module tree
    steps: int  # profiled steps
    wall_ms: float  # median wall time of a step without the profiler

    @property
    def total_ms(self) -> float:
        return sum(row.ms for row in self.rows)

    @property
    def nodes(self) -> int:
        return sum(row.nodes for row in self.rows)


# ----------------------------------------------------------------------------- node -> module
Scope = tuple[str, ...]  # a module path: ("encoder", "backbone"); () outside every module


def name_parts(name: str) -> Scope | None:
    """An exporter name ("/propagation_1/layers.0/Mul_3", or a tensor's "..._output_0") -> its parts without the
    exporter's repeat suffixes (the last part is the op); None for a name the exporter did not write (onnxruntime's,
    a graph input or output, an initializer)."""
    if not name.startswith("/"):
        return None
    return tuple(REPEAT_SUFFIX.sub("", part) for part in name[1:].split("/"))


def module_tree(graph: Any) -> dict[Scope, int]:
    """The exported graph (before onnxruntime's optimisations) -> every module path its node names hold, with the
    position of the module's first node: the order in which the step was traced, i.e. runs its modules."""
    tree: dict[Scope, int] = {(): 0}
    for position, node in enumerate(graph.node):
        parts = name_parts(node.name) or ()
        for level in range(1, len(parts)):
            tree.setdefault(parts[:level], position)
    return tree


def scope_of(name: str, tree: dict[Scope, int]) -> Scope | None:
    """A name -> the longest module path of `tree` it starts with; onnxruntime keeps the exporter's name of what it
    fuses and appends its own ("/head/Gather_1/GatherSliceToSplitFusion": head). None: not the exporter's name."""
    parts = name_parts(name)
    if parts is None:
        return None
    for level in range(len(parts) - 1, 0, -1):
        if parts[:level] in tree:
            return parts[:level]
    return ()


def node_scopes(graph: Any, tree: dict[Scope, int]) -> dict[str, Scope]:
    """Every node of the optimised onnx GraphProto -> its module path: by its name, else the tensors it writes,
    else those it reads, else its producers' or consumers' (repeated until nothing changes), else ()."""
    nodes = list(graph.node)
    scopes: dict[str, Scope] = {}
    for node in nodes:
        for name in [node.name, *node.output, *node.input]:
            scope = scope_of(name, tree)
            if scope is not None:
                scopes[node.name] = scope
                break
    producer = {output: node.name for node in nodes for output in node.output}
    consumers: dict[str, list[str]] = {}
    for node in nodes:
        for name in node.input:
            consumers.setdefault(name, []).append(node.name)
    changed = True
    while changed:  # inserted chains (reorder -> NCHWc conv -> reorder) inherit from the nearest named node
        changed = False
        for node in nodes:
            if node.name in scopes:
                continue
            near = [producer.get(name) for name in node.input]
            near += [c for name in node.output for c in consumers.get(name, [])]
            known = [scopes[n] for n in near if n is not None and n in scopes]
            if known:
                scopes[node.name] = known[0]
                changed = True
    return {node.name: scopes.get(node.name, ()) for node in nodes}


def tree_order(keys: Sequence[str], first_seen: dict[str, int]) -> list[str]:
    """Rows in the order of the module tree: each level by where its module first runs, a module's own nodes
    before its children's, OUTSIDE last. first_seen: every prefix of every row ("head", "head/decoder") -> rank."""

    def key(row: str) -> tuple[float, ...]:
        if row == OUTSIDE:
            return (float("inf"),)
        parts = row.split("/")
        return tuple(float(first_seen.get("/".join(parts[: i + 1]), 1e12)) for i in range(len(parts)))

    return sorted(keys, key=key)


def row_of(node: str, scopes: dict[str, Scope], tree: dict[Scope, int], depth: int) -> str:
    """The row a profiled node is charged to: its module path (node_scopes; else by its own name) cut to `depth`
    levels, or OUTSIDE."""
    scope = scopes[node] if node in scopes else scope_of(node, tree) or ()
    return "/".join(scope[:depth]) or OUTSIDE


def group_rows(
    node_ms: dict[str, float], scopes: dict[str, Scope], tree: dict[Scope, int], depth: int
) -> list[ProfileRow]:
    """Per-node ms per step -> one row per module path cut to `depth` levels, in tree order; every node in exactly
    one row. scopes: node -> module path (node_scopes; a node not there is charged by its own name)."""
    sums: dict[str, float] = {}
    counts: dict[str, int] = {}
    for node, ms in node_ms.items():
        key = row_of(node, scopes, tree, depth)
        sums[key] = sums.get(key, 0.0) + ms
        counts[key] = counts.get(key, 0) + 1
    first_seen = {"/".join(path): position for path, position in tree.items() if path}
    return [ProfileRow(key, sums[key], counts[key]) for key in tree_order(list(sums), first_seen)]


# ----------------------------------------------------------------------------- the profiler
def step_feeds(session: Any) -> dict[str, np.ndarray]:
    """Random inputs of the step graph's own shapes (a batch of one; frame in [0, 1], the cache non-zero: a stream
    past its first frame)."""
    if "config" not in session.get_modelmeta().custom_metadata_map:
        raise ValueError("--profile needs a step graph written by rafd export (its metadata has no config)")
    rng = np.random.default_rng(0)
    return {
        i.name: rng.random([d if isinstance(d, int) else 1 for d in i.shape], dtype=np.float32)
        for i in session.get_inputs()
    }


def open_session(path: Path, threads: int, profile_dir: Path | None = None) -> Any:
    """An onnxruntime session as the service's fp32 backend opens it (rafd.runtime.ort_backend); with profile_dir,
    profiling on and the optimised graph (the nodes the profiler names) written there."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    if profile_dir is not None:
        options.enable_profiling = True
        options.profile_file_prefix = str(profile_dir / "profile")
        options.optimized_model_filepath = str(profile_dir / "optimised.onnx")
        options.log_severity_level = 3  # not the warning that an NCHWc-optimised graph is for this CPU only
    return ort.InferenceSession(str(path), sess_options=options, providers=["CPUExecutionProvider"])


def timed_node_ms(events: list[dict[str, Any]], steps: int) -> dict[str, float]:
    """onnxruntime profile events -> ms per step of each node: the mean over the middle half (by node time) of the
    last `steps` runs, the warm-up's runs before them left out.

    The middle half, not every run: on a shared machine another job's burst slows a few steps a lot, which lifts a
    mean above the median wall time it is compared with; the middle half's mean tracks the median and is still a
    mean, so the rows still add up to the total."""
    runs = sorted(
        (e["ts"], e["ts"] + e["dur"]) for e in events if e.get("cat") == "Session" and e["name"] == "model_run"
    )[-steps:]
    if len(runs) < steps:
        raise RuntimeError(f"the profile holds {len(runs)} runs, expected at least {steps}")
    starts = [start for start, _ in runs]
    per_run: list[dict[str, float]] = [{} for _ in runs]
    for event in events:
        if event.get("cat") == "Node" and event["name"].endswith(KERNEL):
            index = bisect.bisect_right(starts, event["ts"]) - 1
            if index >= 0 and event["ts"] <= runs[index][1]:
                node = event["name"][: -len(KERNEL)]
                per_run[index][node] = per_run[index].get(node, 0.0) + float(event["dur"])
    by_time = sorted(per_run, key=lambda run: sum(run.values()))
    cut = len(by_time) // 4
    middle = by_time[cut : len(by_time) - cut]
    node_us: dict[str, float] = {}
    for run in middle:
        for node, us in run.items():
            node_us[node] = node_us.get(node, 0.0) + us
    return {node: us / 1e3 / len(middle) for node, us in node_us.items()}


def profile_steps(
    paths: dict[str, Path], repeats: int, depth: int, threads: int = PROFILE_THREADS
) -> list[StepProfile]:
    """Each step graph's by-module profile and its wall time, all in one run: per round, one step of each graph
    without the profiler (timed) and one with it, so that load from other jobs, which shifts both, hits every graph
    and both measurements alike (the ratios between graphs and the share covered are of one machine state)."""
    import onnx

    with tempfile.TemporaryDirectory(prefix="rafd-profile-") as tmp:
        plain, profiled, feeds = {}, {}, {}
        for index, (name, path) in enumerate(paths.items()):
            folder = Path(tmp, str(index))
            folder.mkdir()
            plain[name], profiled[name] = open_session(path, threads), open_session(path, threads, folder)
            feeds[name] = step_feeds(plain[name])
            for _ in range(PROFILE_WARMUP):
                plain[name].run(None, feeds[name])
                profiled[name].run(None, feeds[name])
        walls: dict[str, list[float]] = {name: [] for name in paths}
        for _ in range(repeats):
            for name in paths:
                start = time.perf_counter()
                plain[name].run(None, feeds[name])
                walls[name].append(time.perf_counter() - start)
                profiled[name].run(None, feeds[name])
        profiles = []
        for index, (name, path) in enumerate(paths.items()):
            events = json.loads(Path(profiled[name].end_profiling()).read_text())
            node_ms = timed_node_ms(events, repeats)
            tree = module_tree(onnx.load(str(path), load_external_data=False).graph)
            optimised = onnx.load(str(Path(tmp, str(index), "optimised.onnx")), load_external_data=False).graph
            rows = group_rows(node_ms, node_scopes(optimised, tree), tree, depth)
            wall = 1e3 * float(np.median(walls[name]))
            log.info(
                "profiled %s: %d nodes, %.1f ms of node time per step, wall %.1f ms",
                name,
                len(node_ms),
                sum(node_ms.values()),
                wall,
            )
            profiles.append(StepProfile(name, rows, repeats, wall))
    return profiles


def profiler_cost_us(repeats: int, threads: int = PROFILE_THREADS) -> float:
    """The profiler's own cost per node, in µs: a node's profiled kernel time includes the profiler's bookkeeping
    for it (what it records of the node), which shows on nodes of next to no work. Measured on a chain of
    CHAIN_NODES scalar Adds: its profiled kernel time per node less its wall time per node without the profiler."""
    import onnx
    from onnx import helper, numpy_helper

    nodes = [
        helper.make_node("Add", [f"x{i}", "one"], [f"x{i + 1}"], name=f"/chain/Add_{i}") for i in range(CHAIN_NODES)
    ]
    graph = helper.make_graph(
        nodes,
        "chain",
        [helper.make_tensor_value_info("x0", onnx.TensorProto.FLOAT, [1])],
        [helper.make_tensor_value_info(f"x{CHAIN_NODES}", onnx.TensorProto.FLOAT, [1])],
        [numpy_helper.from_array(np.ones(1, np.float32), "one")],
    )
    feeds = {"x0": np.zeros(1, np.float32)}
    with tempfile.TemporaryDirectory(prefix="rafd-profile-") as tmp:
        path = Path(tmp, "chain.onnx")
        onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), str(path))
        plain, profiled = open_session(path, threads), open_session(path, threads, Path(tmp))
        walls = []
        for index in range(PROFILE_WARMUP + repeats):
            start = time.perf_counter()
            plain.run(None, feeds)
            if index >= PROFILE_WARMUP:
                walls.append(time.perf_counter() - start)
            profiled.run(None, feeds)
        node_ms = timed_node_ms(json.loads(Path(profiled.end_profiling()).read_text()), repeats)
    return 1e3 * (sum(node_ms.values()) - 1e3 * float(np.median(walls))) / CHAIN_NODES


# ----------------------------------------------------------------------------- inputs
def recipe_checkpoint(work: Path, name: str) -> Path:
    """A recipe's network (rafd.train.recipes) with random weights: its cost does not depend on them."""
    import torch

    from rafd import build_model, save_checkpoint
    from rafd.train.recipes import recipe_model

    torch.manual_seed(0)
    cfg = recipe_model(name)
    path = work / f"{name}_random.pt"
    save_checkpoint(path, build_model(cfg).eval(), cfg, meta={"note": "random weights for profiling"})
    return path


def step_onnx(checkpoint: Path, work: Path) -> Path:
    """The step ONNX to profile: the file itself when it is one, else the checkpoint exported (no verification)."""
    if checkpoint.suffix == ".onnx":
        return checkpoint
    from export.onnx_export import export_onnx

    output = work / f"{checkpoint.stem}.step.onnx"
    export_onnx(checkpoint, output, batch="static", verify=False, log=log.info)
    return output


# ----------------------------------------------------------------------------- table
def tree_rows(profiles: Sequence[StepProfile]) -> list[str]:
    """The rows of every profile in one tree order (a module first seen in a later profile after the earlier's)."""
    rank: dict[str, int] = {}
    for profile in profiles:
        for row in profile.rows:
            parts = row.module.split("/")
            for level in range(1, len(parts) + 1):
                rank.setdefault("/".join(parts[:level]), len(rank))
    return tree_order(list(dict.fromkeys(row.module for p in profiles for row in p.rows)), rank)


def row_label(module: str, modules: Sequence[str]) -> str:
    """A module's row; "(own ops)" where deeper rows of its children follow, which it does not include."""
    return f"{module} (own ops)" if any(m.startswith(module + "/") for m in modules) else module


def format_profiles(profiles: Sequence[StepProfile], depth: int, machine: str, profiler_us: float | None = None) -> str:
    """The profiles side by side: per module ms per step, share of the TOTAL and nodes; TOTAL (the sum of the rows)
    and below it the wall median, with the TOTAL as a share of it; from the second profile on, its ms over the
    first's."""
    first = profiles[0]
    header = ["module"]
    for profile in profiles:
        header += [f"{profile.name} ms", "%", "nodes"]
    header += [f"{p.name} / {first.name}" for p in profiles[1:]]
    lines = [
        f"machine: {machine}",
        f"onnxruntime fp32, {PROFILE_THREADS} thread, sequential; {first.steps} profiled steps after {PROFILE_WARMUP} "
        "warm-up; a row: the mean ms per step of its nodes over the middle half of the steps by node time, % of the "
        f"TOTAL; modules to depth {depth}; wall: the median of {first.steps} steps without the profiler, interleaved "
        "with the profiled ones",
        "",
        "| " + " | ".join(header) + " |",
        "|" + "---|" * len(header),
    ]

    def ratio(a: float | None, b: float | None) -> str:
        return "-" if a is None or b is None or b <= 0 else f"{a / b:.2f}"

    modules = tree_rows(profiles)
    tables = [{row.module: row for row in p.rows} for p in profiles]
    for module in modules:
        rows = [table.get(module) for table in tables]
        cells = [row_label(module, modules)]
        for row, profile in zip(rows, profiles):
            cells += (
                ["-"] * 3
                if row is None
                else [f"{row.ms:.2f}", f"{100 * row.ms / profile.total_ms:.1f}", str(row.nodes)]
            )
        cells += [ratio(row.ms if row else None, rows[0].ms if rows[0] else None) for row in rows[1:]]
        lines.append("| " + " | ".join(cells) + " |")
    cells = ["**TOTAL** (sum of the rows)"]
    for profile in profiles:
        cells += [f"{profile.total_ms:.2f}", "100", str(profile.nodes)]
    cells += [ratio(p.total_ms, first.total_ms) for p in profiles[1:]]
    lines.append("| " + " | ".join(cells) + " |")
    cells = ["wall median, no profiler"]
    for profile in profiles:
        cells += [f"{profile.wall_ms:.2f}", f"TOTAL = {100 * profile.total_ms / profile.wall_ms:.1f}% of it", ""]
    cells += [ratio(p.wall_ms, first.wall_ms) for p in profiles[1:]]
    lines.append("| " + " | ".join(cells) + " |")
    if profiler_us is not None:
        carried = ", ".join(f"{p.name} {p.nodes * profiler_us / 1e3:.1f} ms" for p in profiles)
        lines += [
            "",
            f"the profiler's own cost, inside each node's time: {profiler_us:.1f} µs per node (a chain of "
            f"{CHAIN_NODES} scalar Adds in this run), so a row of n nodes carries about n x that; the TOTAL: {carried}",
        ]
    return "\n".join(lines)


def profiles_json(profiles: Sequence[StepProfile], depth: int, profiler_us: float | None = None) -> dict[str, Any]:
    """The --json figures of a profile run."""
    return {
        "profile": {
            "depth": depth,
            "profiler_us_per_node": profiler_us,
            "threads": PROFILE_THREADS,
            "warmup": PROFILE_WARMUP,
            "configs": {
                p.name: {
                    "steps": p.steps,
                    "rows": [asdict(row) for row in p.rows],
                    "total_ms": p.total_ms,
                    "wall_ms": p.wall_ms,
                    "covered": p.total_ms / p.wall_ms,
                    "nodes": p.nodes,
                }
                for p in profiles
            },
        }
    }
