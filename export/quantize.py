"""int8 post-training quantization of an exported step graph: MODEL.onnx -> MODEL.int8.onnx, for CPUs with int8
dot-product units (VNNI, AMX), served by OpenVINO behind its own accuracy gate (export/gate.py).

onnxruntime's static quantization in the QDQ form (QuantizeLinear / DequantizeLinear pairs around each quantized
operation, which OpenVINO fuses into its int8 kernels): only the convolutions and the matrix products are quantized
(weights per output channel, int8; activations uint8), so everything else stays float32 - the sampling-position
arithmetic of the flow-guided propagation (the flow scaled and added to the grid, the ego motion's rotation), the
GridSample that reads the past features at those positions, the cost volume's softmax and the box decoding. Of the
matrix operations, those in the float32 islands (units of export.islands.search_units, chosen by the gate's search
where quantizing every one fails: export/islands_gate.py) stay float32 too; the file names them in its metadata
(rafd.model_files.FLOAT32_ISLANDS_KEY). The activation ranges are calibrated on simulated sequences streamed through
the float32 model (the step graph's inputs as the service feeds them, its state included), from a seed apart from
the gate's: the gate then judges on data the calibration never saw.
"""

from __future__ import annotations

import json
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from rafd.model_files import FLOAT32_ISLANDS_KEY, int8_model_path

CALIBRATION_SEED = 7300  # not the gate's (export.gate.DEFAULT_SEED) nor a training or benchmark seed
CALIBRATION_SEQUENCES, CALIBRATION_FRAMES = 4, 30  # simulated sequences streamed for the activation ranges
# the rest of the graph stays float32 (the module docstring says why); Gemm: a MatMul and its Add, as onnxruntime's
# pre-processing fuses them (the name keeps the MatMul's: ".../MatMul/MatMulAddFusion")
QUANTIZED_OPS = ("Conv", "MatMul", "Gemm")


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
    from export.gate import simulated_sequences
    from rafd.runtime import OnnxRunner

    runner = OnnxRunner(onnx_path, threads=None)
    recording = _RecordingBackend(runner.backend)
    runner.backend = recording  # the same interface, recording on the way
    for sequence in simulated_sequences(runner.config, sequences, frames, seed):
        state = runner.new_state()
        for item in sequence:
            _, state = runner.step(state, item.frame, item.pose)
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
    """What quantizing any set of a model's matrix operations needs, made once (calibrate): the model prepared for
    quantization (shapes inferred, constants folded) and its activation ranges (onnxruntime's calibration cache,
    which covers every matrix operation's tensors: the ranges are the float model's, whatever is quantized)."""

    source: Path
    prepared: Path
    ranges: Path


def calibrate(
    onnx_path: str | Path,
    folder: str | Path,
    sequences: int = CALIBRATION_SEQUENCES,
    frames: int = CALIBRATION_FRAMES,
    seed: int = CALIBRATION_SEED,
    log: Callable[[str], None] = lambda _: None,
) -> Calibration:
    """Prepare `onnx_path` for quantization and calibrate its activation ranges on simulated sequences, into
    `folder` (which the caller owns)."""
    from onnxruntime.quantization.shape_inference import quant_pre_process

    folder = Path(folder)
    feeds = calibration_feeds(onnx_path, sequences, frames, seed)
    calibration = Calibration(Path(onnx_path), folder / "prepared.onnx", folder / "ranges.json")
    quant_pre_process(str(onnx_path), str(calibration.prepared))
    # onnxruntime calibrates inside quantize_static and keeps the ranges in its cache file: one quantization of every
    # matrix operation makes them, and every later quantization reads them instead of calibrating again
    _quantize(calibration, folder / "every.int8.onnx", None, feeds)
    log(f"int8 calibration: {len(feeds)} steps of {sequences} simulated sequences (seed {seed})")
    return calibration


def _quantize(
    calibration: Calibration, out: Path, nodes: list[str] | None, feeds: list[dict[str, np.ndarray]] | None = None
) -> None:
    """onnxruntime's static QDQ quantization of the prepared model's `nodes` (None: every matrix operation) into
    `out`, from the cached ranges (calibrating on `feeds` first when given)."""
    from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static

    class Feeds(CalibrationDataReader):  # type: ignore[misc]  # onnxruntime's quantization is untyped
        def __init__(self, feeds: list[dict[str, np.ndarray]]) -> None:
            self.remaining = iter(feeds)

        def get_next(self) -> dict[str, np.ndarray] | None:
            return next(self.remaining, None)

    quantize_static(
        str(calibration.prepared),
        str(out),
        Feeds(feeds) if feeds is not None else None,
        quant_format=QuantFormat.QDQ,
        op_types_to_quantize=list(QUANTIZED_OPS),
        nodes_to_quantize=nodes,
        per_channel=True,
        activation_type=QuantType.QUInt8,
        weight_type=QuantType.QInt8,
        calibration_cache_path=str(calibration.ranges),
    )


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
    (calibrate), so that a search quantizing many sets calibrates once; without it, calibrated here."""
    import onnx

    source = Path(onnx_path)
    target = Path(out) if out is not None else int8_model_path(source)
    with tempfile.TemporaryDirectory(prefix="rafd-quantize-") as tmp:
        if calibration is None:
            calibration = calibrate(source, tmp, log=log)
        elif calibration.source.resolve() != source.resolve():
            raise ValueError(f"the calibration is {calibration.source}'s, not {source}'s")
        nodes = quantized_nodes(onnx.load(str(calibration.prepared), load_external_data=False), islands)
        if not nodes:  # onnxruntime reads an empty list as "every node"
            raise ValueError(f"nothing left to quantize: every matrix operation lies in the islands {islands}")
        quantized = Path(tmp, "int8.onnx")
        _quantize(calibration, quantized, nodes)
        model = onnx.load(str(quantized))
        original = {p.key: p.value for p in onnx.load(str(source), load_external_data=False).metadata_props}
        original[FLOAT32_ISLANDS_KEY] = json.dumps(list(islands))
        kept = {p.key for p in model.metadata_props}
        for key, value in original.items():
            if key not in kept and not key.startswith("gate_"):  # the gate records are the float model's
                model.metadata_props.add(key=key, value=value)
        tmp_target = target.with_name(f".{target.name}.tmp")
        onnx.save(model, str(tmp_target))
        tmp_target.replace(target)
    return target
