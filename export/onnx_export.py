"""Checkpoint -> ONNX (the model's streaming step, export.step) with metadata, onnx.checker and onnxruntime parity
verification."""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import onnx
import torch

import rafd
from export import MIN_OPSET
from export.gate import gate_metadata, put_in_place, run_export_gates
from export.gate_options import GateOptions
from export.gate_report import GateReport
from export.step import StepGraph, build_graph
from export.verify import Report, verify_export
from rafd.config import RaFDConfig
from rafd.model.checkpoint import load_checkpoint
from rafd.model_files import file_sha256, int8_model_path, islands_dir
from rafd.protocol import FAR_THRESHOLD_KEY, OPERATING_THRESHOLD_KEY, check_score_threshold, far_threshold

BATCH_MODES = ("static", "dynamic")


class ExportError(RuntimeError):
    """The export cannot be done (bad output path, exporter failure, invalid graph)."""


@dataclass
class ExportResult:
    path: Path
    opset: int
    exporter: str  # "torchscript" (torch.onnx.export dynamo=False) or "dynamo"
    export_seconds: float  # torch.onnx.export + metadata + onnx.checker
    verify_seconds: float
    size_bytes: int
    metadata: dict[str, str]
    report: Report | None
    gates: dict[str, GateReport] = field(default_factory=dict)  # reduced precision -> accuracy gate


def check_output_path(output: Path) -> None:
    """Fail before the (slow) export when the output cannot be written."""
    if output.is_dir():
        raise ExportError(f"output path {output} is a directory")
    parent = output.parent
    if not parent.is_dir():
        raise ExportError(f"cannot write {output}: {parent} is not an existing directory")
    try:  # os.access is not enough (root, read-only mounts): really create a file there
        with tempfile.NamedTemporaryFile(dir=parent, prefix=f".{output.name}.", suffix=".probe"):
            pass
    except OSError as error:
        raise ExportError(f"cannot write {output}: {error.strerror or error}") from error


def build_metadata(
    cfg: RaFDConfig,
    checkpoint_sha256: str,
    opset: int,
    exporter: str,
    operating_threshold: float | None = None,
    batch: str = "static",
    far: Any = None,
) -> dict[str, str]:
    """rafd.runtime.METADATA_KEYS (+ opset, exporter, and the checkpoint's operating threshold when it has one, chosen
    by `rafd-eval --calibrate`, with its far threshold from `--calibrate-far`): everything the service needs besides
    the graph."""
    optional = (
        {}
        if operating_threshold is None
        else {
            OPERATING_THRESHOLD_KEY: repr(
                check_score_threshold(operating_threshold, "the checkpoint's operating threshold")
            )
        }
    )
    parsed = far_threshold(far)
    if parsed is not None and operating_threshold is not None:
        from_m, threshold = parsed
        check_score_threshold(threshold, "the checkpoint's far operating threshold")
        optional[FAR_THRESHOLD_KEY] = json.dumps({"from_m": from_m, "threshold": threshold})
    return optional | {
        "config": cfg.to_json(),
        "input_size": str(cfg.input_size),
        "resolution": repr(float(cfg.resolution)),
        "num_frames": str(cfg.num_frames),
        "class_names": json.dumps(list(cfg.class_names)),
        "checkpoint_sha256": checkpoint_sha256,
        "version": rafd.__version__,
        "opset": str(opset),
        "exporter": exporter,
        "batch": batch,
    }


def _torch_export(
    graph: StepGraph,
    inputs: tuple[torch.Tensor, ...],
    path: Path,
    opset: int,
    log: Callable[[str], None],
    batch: str = "static",
) -> str:
    """torch.onnx.export with static shapes (batch "dynamic": a free first axis on every input and output, the rest
    static): the TorchScript exporter first (robust with grid_sample), then dynamo."""
    input_names, output_names = list(graph.input_names), list(graph.output_names)
    names: dict[str, Any] = dict(  # keyword arguments of both exporters
        input_names=input_names, output_names=output_names, opset_version=opset
    )
    if batch == "dynamic":
        names["dynamic_axes"] = {name: {0: "batch"} for name in input_names + output_names}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the TorchScript exporter's deprecation / tracer warnings
            torch.onnx.export(graph, inputs, str(path), dynamo=False, do_constant_folding=True, **names)
        return "torchscript"
    except Exception as error:  # noqa: BLE001 - any exporter failure: try the other exporter
        log(f"TorchScript exporter failed ({type(error).__name__}: {error}); trying the dynamo exporter")
    try:
        program = torch.onnx.export(graph, inputs, dynamo=True, external_data=False, optimize=True, **names)
        assert program is not None  # dynamo=True returns the program
        program.save(str(path))
        return "dynamo"
    except Exception as error:  # noqa: BLE001
        raise ExportError(f"torch.onnx.export failed with both exporters: {type(error).__name__}: {error}") from error


def _restore_unused_inputs(
    proto: onnx.ModelProto, names: tuple[str, ...], example: tuple[torch.Tensor, ...], batch: str
) -> None:
    """The exporters drop inputs the graph does not use (pose for T = 1); the contract keeps them."""
    present = {value.name: onnx.ValueInfoProto.FromString(value.SerializeToString()) for value in proto.graph.input}

    def shape(tensor: torch.Tensor) -> list[int | str]:
        return ["batch" if batch == "dynamic" and axis == 0 else size for axis, size in enumerate(tensor.shape)]

    inputs = [
        present.get(name) or onnx.helper.make_tensor_value_info(name, onnx.TensorProto.FLOAT, shape(tensor))
        for name, tensor in zip(names, example)
    ]
    del proto.graph.input[:]
    proto.graph.input.extend(inputs)


def _declare_output_shapes(proto: onnx.ModelProto, names: tuple[str, ...], example: tuple[torch.Tensor, ...]) -> None:
    """Every output's static shape as PyTorch computes it (the exporters leave some symbolic after a Reshape on a
    free batch axis), the batch axis as the inputs have it: a runtime can then check that new_cache.NAME fits
    cache.NAME, and OpenVINO compiles static shapes."""
    batch = proto.graph.input[0].type.tensor_type.shape.dim[0]
    for value, tensor in zip(proto.graph.output, example):
        assert value.name in names
        dims = value.type.tensor_type.shape.dim
        del dims[:]
        for axis, size in enumerate(tensor.shape):
            dim = dims.add()
            if axis == 0:
                dim.CopyFrom(batch)
            else:
                dim.dim_value = size


def export_onnx(
    checkpoint: str | os.PathLike[str],
    output: str | os.PathLike[str],
    opset: int = MIN_OPSET,
    verify: bool = True,
    log: Callable[[str], None] = print,
    gate: GateOptions | None = None,
    batch: str = "dynamic",
) -> ExportResult:
    """Export a checkpoint; the output appears (atomically) only when checker and verification passed.

    gate: also run the accuracy gate of every reduced precision this CPU runs and record
    "gate_<precision>" = pass / fail (+ "gate_<precision>_figures", JSON) in the metadata, which is what lets
    rafd.runtime.create_runner pick that precision automatically.

    batch: "static" (batch of one, the smallest graph) or "dynamic" (a free first axis, so the views of one stream,
    the tiles of a whole scan, step as one batch; verified batched as well).

    Raises rafd.model.checkpoint.CheckpointError (bad checkpoint), ExportError, export.verify.VerificationError.
    """
    checkpoint, output = Path(checkpoint), Path(output)
    if opset < MIN_OPSET:
        raise ExportError(f"opset {opset} is too old: RaFD needs opset >= {MIN_OPSET}")
    if batch not in BATCH_MODES:
        raise ExportError(f"batch must be one of {BATCH_MODES}, got {batch!r}")
    check_output_path(output)
    model, cfg, meta = load_checkpoint(checkpoint)
    model = model.eval()
    sha = file_sha256(checkpoint)
    operating_threshold = meta.get(OPERATING_THRESHOLD_KEY) if isinstance(meta, dict) else None

    start = time.perf_counter()
    graph, example = build_graph(model, cfg)
    tmp = output.with_name(f".{output.name}.{os.getpid()}.tmp")
    try:
        with tempfile.TemporaryDirectory(dir=output.parent, prefix=f".{output.name}.") as workdir:
            raw = Path(workdir, "raw.onnx")
            with torch.no_grad():
                exporter = _torch_export(graph, example, raw, opset, log, batch)
            proto = onnx.load(str(raw))  # also pulls in external data, if the exporter wrote any
        _restore_unused_inputs(proto, graph.input_names, example, batch)
        with torch.no_grad():
            _declare_output_shapes(proto, graph.output_names, graph(*example))
        far = meta.get(FAR_THRESHOLD_KEY) if isinstance(meta, dict) else None
        metadata = build_metadata(cfg, sha, opset, exporter, operating_threshold, batch, far)
        del proto.metadata_props[:]
        for key, value in metadata.items():
            proto.metadata_props.add(key=key, value=value)
        try:
            onnx.checker.check_model(proto, full_check=True)
        except (onnx.checker.ValidationError, onnx.shape_inference.InferenceError) as error:
            raise ExportError(f"onnx.checker rejected the exported graph: {error}") from error
        onnx.save(proto, str(tmp))
        del proto
        export_seconds = time.perf_counter() - start
        size = tmp.stat().st_size
        log(
            f"exported the step graph with the {exporter} exporter, opset {opset}: {size / 1e6:.2f} MB "
            f"in {export_seconds:.1f} s"
        )

        report, verify_seconds = None, 0.0
        if verify:
            start = time.perf_counter()
            report = verify_export(tmp, model, cfg, log=log)
            verify_seconds = time.perf_counter() - start
        gates: dict[str, GateReport] = {}
        if gate is not None:
            gates = run_export_gates(tmp, gate, log)
            if gates:  # record the verdicts in the file itself: the service reads them
                proto = onnx.load(str(tmp))
                for key, value in gate_metadata(gates).items():
                    proto.metadata_props.add(key=key, value=value)
                    metadata[key] = value
                onnx.save(proto, str(tmp))
                del proto
                size = tmp.stat().st_size
        # the judged int8 model and bf16 segments were made beside the temporary file: they go with the output
        put_in_place(tmp, output)
    finally:
        tmp.unlink(missing_ok=True)
        int8_model_path(tmp).unlink(missing_ok=True)
        shutil.rmtree(islands_dir(tmp), ignore_errors=True)
    return ExportResult(
        path=output,
        opset=opset,
        exporter=exporter,
        export_seconds=export_seconds,
        verify_seconds=verify_seconds,
        size_bytes=size,
        metadata=metadata,
        report=report,
        gates=gates,
    )
