"""int8 post-training quantization of an exported step graph: MODEL.onnx -> MODEL.int8.onnx, for CPUs with int8
dot-product units (VNNI, AMX), served by OpenVINO behind its own accuracy gate (export/gate.py).

NNCF's static quantization (its ONNX backend: QuantizeLinear / DequantizeLinear pairs on the inputs of each
quantized operation, placed as OpenVINO fuses them into its int8 kernels; weights per output channel, symmetric):
only the convolutions and the matrix products are quantized, so everything else stays float32 - the
sampling-position arithmetic of the flow-guided propagation (the flow scaled and added to the grid, the ego motion's
rotation), the GridSample that reads the past features at those positions, the softmaxes and the box decoding. Of
the matrix operations, those in the float32 islands (units of export.islands.search_units, chosen by the gate's
search where quantizing every one fails: export/islands_gate.py) stay float32 too; the file names them in its
metadata (rafd.model_files.FLOAT32_ISLANDS_KEY). NNCF, not onnxruntime's quantize_static: OpenVINO ran the latter's
graphs slower than float32 (docs/archive.md, "int8: why NNCF"). The activation
statistics come from simulated sequences streamed through the float32 model (the step graph's inputs as the service
feeds them, its state included), from a seed apart from the gate's: the gate then judges on data the calibration
never saw.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rafd.model_files import FLOAT32_ISLANDS_KEY, int8_model_path
from rafd.progress import stage

CALIBRATION_SEED = 7300  # not the gate's (export.gate_options.DEFAULT_SEED) nor a training or benchmark seed
CALIBRATION_SEQUENCES, CALIBRATION_FRAMES = 4, 30  # simulated sequences streamed for the activation ranges
QUANTIZED_OPS = ("Conv", "MatMul", "Gemm")  # the rest of the graph stays float32 (the module docstring says why)


class _RecordingBackend:
    """A runner's backend that keeps the feeds of every run (the calibration inputs)."""

    def __init__(self, backend: Any) -> None:
        self.backend = backend
        self.feeds: list[dict[str, np.ndarray]] = []

    def __getattr__(self, name: str) -> Any:
        return getattr(self.backend, name)

    def run(self, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        self.feeds.append({name: np.array(value, copy=True) for name, value in feeds.items()})
        outputs: dict[str, np.ndarray] = self.backend.run(feeds)
        return outputs


def calibration_feeds(
    onnx_path: str | Path,
    sequences: int = CALIBRATION_SEQUENCES,
    frames: int = CALIBRATION_FRAMES,
    seed: int = CALIBRATION_SEED,
) -> list[dict[str, np.ndarray]]:
    """The step graph's inputs over `sequences` simulated sequences of `frames` frames, state included."""
    from export.gate_drives import simulated_sequences
    from rafd.runtime import OnnxRunner

    runner = OnnxRunner(onnx_path, threads=None)
    recording = _RecordingBackend(runner.backend)
    runner.backend = recording  # the same interface, recording on the way
    for sequence in simulated_sequences(runner.config, sequences, frames, seed):
        state = runner.new_state()
        for item in sequence:
            _, state = runner.step(state, item.frame[None], item.pose[None])
    return recording.feeds


def quantized_nodes(proto: Any, islands: tuple[str, ...]) -> list[str]:
    """The names of the nodes quantization turns into int8 kernels: the matrix operations (QUANTIZED_OPS) outside
    the float32 islands (export.islands.in_scope)."""
    from export.islands import in_scope

    return [
        n.name
        for n in proto.graph.node
        if n.op_type in QUANTIZED_OPS and not any(in_scope(n.name, island) for island in islands)
    ]


@dataclass(frozen=True)
class Calibration:
    """What quantizing any set of a model's islands needs, made once for every set a search tries: the model
    prepared for quantization and its calibration inputs (calibration_feeds; the activation statistics are the float
    model's, whatever is quantized)."""

    source: Path
    prepared: Any  # onnx.ModelProto (an untyped library)
    feeds: list[dict[str, np.ndarray]]


def calibrate(
    onnx_path: str | Path,
    sequences: int = CALIBRATION_SEQUENCES,
    frames: int = CALIBRATION_FRAMES,
    seed: int = CALIBRATION_SEED,
    log: Callable[[str], None] = lambda _: None,
) -> Calibration:
    """Prepare `onnx_path` for quantization and stream it over simulated sequences, keeping its inputs."""
    import onnx

    feeds = calibration_feeds(onnx_path, sequences, frames, seed)
    log(f"int8 calibration: {len(feeds)} steps of {sequences} simulated sequences (seed {seed})")
    return Calibration(Path(onnx_path), prepared_for_quantization(onnx.load(str(onnx_path))), feeds)


@contextlib.contextmanager
def _quiet_nncf() -> Iterator[None]:
    """NNCF's per-node notes and its progress bars (rich, on stdout) held back while it runs: the stage line and the
    gate say what runs. Only its logger's level is changed, and back (nncf.set_log_level would also set the level of
    every handler on that logger, which may be another's: pytest's capture handlers were)."""
    nncf_log = logging.getLogger("nncf")
    level = nncf_log.level
    nncf_log.setLevel(logging.ERROR)
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            yield
    finally:
        nncf_log.setLevel(level)


def prepared_for_quantization(proto: Any) -> Any:
    """The graph without its no-op nodes, every other node keeping its name (the islands match names by prefix):
    the exporter routes a weight shared by several calls (the propagation's layers over the past frames) through
    Identity nodes, and NNCF quantizes only a convolution whose weights are a constant; and it writes Casts to the
    type a value already has, which NNCF 3.4 removes itself, but not where one yields a graph output (the step's
    flow_features: its pass fails). onnx-ir's IdentityEliminationPass removes both, keeping the output names."""
    import onnx
    import onnx_ir as ir
    from onnx_ir.passes.common import IdentityEliminationPass

    inferred = onnx.shape_inference.infer_shapes(proto)
    graph = inferred.graph
    types = {v.name: v.type.tensor_type.elem_type for v in (*graph.value_info, *graph.input, *graph.output)}
    types.update({t.name: t.data_type for t in graph.initializer})
    for node in graph.node:
        to = next((a.i for a in node.attribute if a.name == "to"), None)
        if node.op_type == "Cast" and to is not None and types.get(node.input[0]) == to:
            node.op_type = "Identity"
            del node.attribute[:]
    return ir.serde.serialize_model(IdentityEliminationPass()(ir.serde.deserialize_model(inferred)).model)


def quantize_model(
    onnx_path: str | Path,
    out: str | Path | None = None,
    islands: tuple[str, ...] = (),
    calibration: Calibration | None = None,
    log: Callable[[str], None] = lambda _: None,
) -> Path:
    """Write the int8 model (default: beside the model, rafd.model_files.int8_model_path) -> its path, every matrix
    operation quantized but those in `islands` (units of export.islands.search_units, kept float32). The ONNX
    metadata (config, graph contract) is carried over, so it reads as the same model. `calibration`: the model's
    (calibrate), so that a search quantizing many sets streams the simulation once; without it, calibrated here."""
    import nncf
    import onnx

    from export.islands import scope_pattern

    source = Path(onnx_path)
    target = Path(out) if out is not None else int8_model_path(source)
    if calibration is None:
        calibration = calibrate(source, log=log)
    elif calibration.source.resolve() != source.resolve():
        raise ValueError(f"the calibration is {calibration.source}'s, not {source}'s")
    proto = calibration.prepared
    if not quantized_nodes(proto, islands):
        raise ValueError(f"nothing left to quantize: every matrix operation lies in the islands {islands}")
    # Every operation but the matrix ones is left alone (by type), and the islands' matrix operations too (by name):
    # NNCF quantizes the inputs of what remains, weights per channel, both symmetric (its performance preset).
    ignored = nncf.IgnoredScope(
        types=sorted({n.op_type for n in proto.graph.node} - set(QUANTIZED_OPS)),
        patterns=[scope_pattern(island) for island in islands],
        validate=False,  # a graph need not hold every type or island named
    )
    stage(f"int8: quantizing {source.name} with NNCF ({len(islands)} float32 islands)")
    with _quiet_nncf():
        model = nncf.quantize(
            proto,
            nncf.Dataset(calibration.feeds),
            preset=nncf.QuantizationPreset.PERFORMANCE,
            subset_size=len(calibration.feeds),
            ignored_scope=ignored,
        )
    original = {p.key: p.value for p in onnx.load(str(source), load_external_data=False).metadata_props}
    original[FLOAT32_ISLANDS_KEY] = json.dumps(list(islands))
    del model.metadata_props[:]
    for key, value in original.items():
        if not key.startswith("gate_"):  # the gate records are the float model's
            model.metadata_props.add(key=key, value=value)
    tmp_target = target.with_name(f".{target.name}.tmp")
    onnx.save(model, str(tmp_target))
    tmp_target.replace(target)
    return target
