"""bf16 with float32 islands: an exported step graph cut into consecutive segments, each whole in one precision, so
OpenVINO can compile the islands in float32 and the rest in bf16.

Why segments and not per-node marks: OpenVINO 2026.4's CPU plugin does not honour the `precise_0` rt_info mark under
bf16 (docs/archive.md), so the only way to keep a node in float32 is to compile
it in a float32 model. An island is a module scope of the export's node names: "/head/heatmap/" is every node under it,
"/propagation/*" the nodes directly in it (the module's own arithmetic, not its layers'), "/*" those at the top. The
search (export/islands_gate.py) judges the graph's units (search_units) by measurement.

Written beside the model as MODEL.bf16-islands/ (rafd.model_files.islands_dir): segment_K.onnx per segment and
segments.json, the manifest the runtime chains them by (rafd.runtime.openvino_islands).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import tempfile
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rafd.model_files import ISLANDS_MANIFEST, islands_dir


@dataclass(frozen=True)
class Segment:
    precision: str  # "fp32" (an island) or "bf16"
    nodes: tuple[int, ...]  # indices into the graph's node list, in a topological order
    inputs: tuple[str, ...]  # the values it reads from the graph's inputs or from earlier segments
    outputs: tuple[str, ...]  # the values later segments or the graph's outputs read from it


def module_scopes(proto: Any) -> list[str]:
    """The top-level module scopes of an exported graph's node names ("/encoder/", "/flow/", ...), in graph order:
    the candidate islands."""
    scopes: list[str] = []
    for node in proto.graph.node:
        parts = node.name.split("/")
        if node.name.startswith("/") and len(parts) > 2 and f"/{parts[1]}/" not in scopes:
            scopes.append(f"/{parts[1]}/")
    return scopes


# what bf16 speeds up (AMX tiles, avx512_bf16 dot products)
MATRIX_OPS = frozenset({"Conv", "ConvTranspose", "MatMul", "Gemm"})


def in_scope(name: str, island: str) -> bool:
    """Whether the node `name` lies in the island: under "/a/b/", or directly in "/a/*" (the rest has no "/")."""
    if island.endswith("/*"):
        return name.startswith(island[:-1]) and "/" not in name[len(island) - 1 :]
    return name.startswith(island)


def scope_pattern(island: str) -> str:
    """The regular expression matching the node names in_scope(name, island) accepts (NNCF's ignored scopes)."""
    if island.endswith("/*"):
        return "^" + re.escape(island[:-1]) + "[^/]*$"
    return "^" + re.escape(island)


def unit_of(name: str, depth: int = 2) -> str | None:
    """The search unit of a node name: the module `depth` levels down it lies under ("/flow/match/" at depth 2), or
    the scope it lies directly in ("/flow/*", "/*"); None for an unnamed node (the exporter's constants and weight
    Identities)."""
    if not name.startswith("/"):
        return None
    parts = name.split("/")[1:-1]  # the scopes, the op's own name dropped
    if len(parts) >= depth:
        return "/" + "/".join(parts[:depth]) + "/"
    return "/" + "".join(f"{p}/" for p in parts) + "*"


def search_units(proto: Any, depth: int = 2) -> tuple[list[str], list[str]]:
    """(matrix_free, matrix): the graph's units (unit_of at `depth`) in graph order, parted by whether a unit holds a
    matrix operation. Reduced precision gains nothing in the matrix-free ones, and they hold the poses, the sampling
    positions, GridSample and the decode's top-k, where bf16's rounding moves things most."""
    constant = constant_values(proto)
    units: dict[str, bool] = {}
    for node in proto.graph.node:
        unit = unit_of(node.name, depth)
        if unit is not None and not set(node.output) <= constant:
            units[unit] = units.get(unit, False) or node.op_type in MATRIX_OPS
    return [u for u, matrix in units.items() if not matrix], [u for u, matrix in units.items() if matrix]


def _precision(node: Any, islands: tuple[str, ...]) -> str:
    return "fp32" if any(in_scope(node.name, island) for island in islands) else "bf16"


def split(proto: Any, islands: Iterable[str]) -> list[Segment]:
    """Cut the graph into as few consecutive single-precision segments as a greedy topological order gives: keep
    emitting ready nodes of the current segment's precision, switch only when none is ready. Constant nodes, and nodes
    computed from constants and initializers alone (an exporter's Identity of a weight), belong to no segment: each
    segment that reads one gets its own copy, so a constant never crosses a cut (OpenVINO folds such a node and
    drops its name, so a segment could not return it)."""
    islands = tuple(islands)
    unknown = sorted(scope for scope in islands if not any(in_scope(n.name, scope) for n in proto.graph.node))
    if unknown:
        raise ValueError(f"no node in {unknown} in this graph (its top-level scopes: {module_scopes(proto)})")
    nodes = list(proto.graph.node)
    constant = constant_values(proto)
    available = {i.name for i in proto.graph.input} | {t.name for t in proto.graph.initializer} | constant | {""}
    pending = [i for i, node in enumerate(nodes) if not set(node.output) <= constant]
    order: list[tuple[str, int]] = []
    current = None
    while pending:
        ready = [i for i in pending if all(name in available for name in nodes[i].input)]
        if not ready:
            raise ValueError("the graph is not in a form the split can order (a node's input is never produced)")
        same = [i for i in ready if _precision(nodes[i], islands) == current]
        index = (same or ready)[0]
        current = _precision(nodes[index], islands)
        order.append((current, index))
        available.update(nodes[index].output)
        pending.remove(index)
    runs: list[tuple[str, list[int]]] = []
    for precision, index in order:
        if runs and runs[-1][0] == precision:
            runs[-1][1].append(index)
        else:
            runs.append((precision, [index]))
    return _segments(proto, runs, constant)


def constant_values(proto: Any) -> set[str]:
    """The values the graph computes from constants alone: Constant nodes' outputs and, in graph order, the outputs
    of nodes whose every input is an initializer or such a value."""
    fixed = {t.name for t in proto.graph.initializer} | {""}
    constant: set[str] = set()
    for node in proto.graph.node:
        if node.op_type == "Constant" or all(name in fixed or name in constant for name in node.input):
            constant.update(node.output)
    return constant


def _segments(proto: Any, runs: list[tuple[str, list[int]]], constant: set[str]) -> list[Segment]:
    """Each run's inputs (read, not produced inside, not a constant or initializer) and outputs (read by a later run
    or a graph output)."""
    nodes = list(proto.graph.node)
    fixed = {t.name for t in proto.graph.initializer} | constant | {""}
    graph_outputs = [o.name for o in proto.graph.output]
    produced = [{out for i in indices for out in nodes[i].output} for _, indices in runs]
    read = [{name for i in indices for name in nodes[i].input} - fixed for _, indices in runs]
    segments = []
    for k, (precision, indices) in enumerate(runs):
        later = set().union(*read[k + 1 :]) | set(graph_outputs)
        inputs = sorted(read[k] - produced[k])
        outputs = sorted(produced[k] & later)
        segments.append(Segment(precision, tuple(indices), tuple(inputs), tuple(outputs)))
    return segments


def segment_models(proto: Any, segments: list[Segment]) -> list[Any]:
    """One ONNX model per segment, extracted between its inputs and outputs by onnx.utils.Extractor (which walks
    back from the outputs and copies the nodes, constants and initializers they need). The Extractor types a
    segment's inputs and outputs from value_info: onnx's shape inference, with the cut values' shapes measured
    (cut_value_infos), since inference leaves some of their dimensions unknown and OpenVINO's batch-1 compilation
    needs them."""
    import onnx.shape_inference
    import onnx.utils

    inferred = onnx.shape_inference.infer_shapes(proto)
    ends = {i.name for i in proto.graph.input} | {o.name for o in proto.graph.output}
    cuts = sorted({name for s in segments for name in s.inputs + s.outputs} - ends)
    measured = cut_value_infos(proto, inferred, cuts)
    kept = [v for v in inferred.graph.value_info if v.name not in measured]
    del inferred.graph.value_info[:]
    inferred.graph.value_info.extend(kept + list(measured.values()))
    extractor = onnx.utils.Extractor(inferred)
    return [extractor.extract_model(list(s.inputs), list(s.outputs)) for s in segments]


def cut_value_infos(proto: Any, inferred: Any, names: list[str]) -> dict[str, Any]:
    """name -> ValueInfoProto of each value, its shape measured by running the whole graph on onnxruntime (zeros;
    a batch of 1, and of 2 where the graph's inputs leave the batch free: the dimensions that differ are the batch
    axis, "batch" as in the graph's inputs), its element type from shape inference."""
    import onnx
    import onnx.helper
    import onnxruntime as ort

    if not names:
        return {}
    types = {v.name: v.type.tensor_type.elem_type for v in inferred.graph.value_info}
    probe = onnx.ModelProto()
    probe.CopyFrom(proto)
    del probe.graph.output[:]
    probe.graph.output.extend(onnx.helper.make_tensor_value_info(name, types[name], None) for name in names)
    session = ort.InferenceSession(probe.SerializeToString(), providers=["CPUExecutionProvider"])
    inputs = session.get_inputs()
    free = any(not isinstance(d, int) for i in inputs for d in i.shape)

    def run(batch: int) -> list[tuple[int, ...]]:
        feeds = {
            i.name: np.zeros([d if isinstance(d, int) else batch for d in i.shape], dtype=np.float32) for i in inputs
        }
        return [tuple(np.shape(array)) for array in session.run(names, feeds)]

    ones = run(1)
    twos = run(2) if free else ones
    out = {}
    for name, one, two in zip(names, ones, twos):
        dims = [a if a == b else "batch" for a, b in zip(one, two)]
        out[name] = onnx.helper.make_tensor_value_info(name, types[name], dims)
    return out


def replace_dir(source: Path, target: Path) -> None:
    """Move the folder `source` to `target`, in place of any folder there (both on one file system)."""
    if target.exists():
        shutil.rmtree(target)
    os.replace(source, target)


def write_islands(onnx_path: str | os.PathLike[str], islands: Iterable[str], folder: Path | None = None) -> Path:
    """Write MODEL.bf16-islands/ (or `folder`): the segments with `islands` in float32, and the manifest. Atomic:
    written into a temporary folder beside it, then put in place of any earlier one. Returns the folder."""
    import onnx

    islands = tuple(islands)
    proto = onnx.load(str(onnx_path))
    segments = split(proto, islands)
    target = Path(folder) if folder is not None else islands_dir(onnx_path)
    work = Path(tempfile.mkdtemp(dir=target.parent, prefix=f".{target.name}."))
    os.chmod(work, 0o755)  # mkdtemp's 0700 would hide the segments from a service running as another user
    try:
        entries = []
        for k, (segment, model) in enumerate(zip(segments, segment_models(proto, segments))):
            name = f"segment_{k}.onnx"
            onnx.save(model, str(work / name))
            entries.append(
                {
                    "file": name,
                    "precision": segment.precision,
                    "inputs": list(segment.inputs),
                    "outputs": list(segment.outputs),
                    "nodes": len(segment.nodes),
                }
            )
        manifest = {"islands": list(islands), "segments": entries}
        (work / ISLANDS_MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")
        replace_dir(work, target)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return target
