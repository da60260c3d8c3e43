"""OpenVINO CPU backend (the native `openvino` package): float32, bf16, or int8 from the quantized model.

Chosen over onnxruntime's OpenVINO execution provider by measurement (same bf16 speed on the paper step graph
here, see docs/performance.md), and because `onnxruntime-openvino` installs a second `onnxruntime`
module over the reference one. OpenVINO reads the ONNX file directly, metadata included (rt_info "framework").
bf16 runs on avx512_bf16 (and AMX where present); OpenVINO keeps precision-sensitive parts in float32 itself.
int8 runs MODEL.int8.onnx (rafd.model_files.int8_model_path: the same graph with its convolutions and matrix products
quantized, QuantizeLinear / DequantizeLinear pairs that OpenVINO fuses into int8 kernels; export/quantize.py) and
the rest in float32; its metadata (config, gate records) is read from MODEL.onnx, the model the gate judged it
against.
"""

from __future__ import annotations

import json
import os
import queue
import threading
from pathlib import Path
from typing import Any

import numpy as np

from rafd.model_files import FLOAT32_ISLANDS_KEY, int8_model_path
from rafd.runtime.backend import DYNAMIC, shapes_at

# The inference precision hint per precision: int8 is in the quantized graph itself, the rest of it runs in float32.
OV_PRECISION = {"fp32": "f32", "bf16": "bf16", "int8": "f32"}


def openvino_supports_bf16() -> bool:
    """Whether OpenVINO's CPU plugin can compute in bf16 on this CPU (False when openvino is not installed)."""
    try:
        import openvino as ov
    except ImportError:
        return False
    return "BF16" in ov.Core().get_property("CPU", "OPTIMIZATION_CAPABILITIES")


def runtime_precisions(compiled: Any) -> dict[tuple[str, str], int]:
    """(layer type, precision it runs in) -> how many nodes of the compiled model's runtime graph: what OpenVINO's CPU
    plugin really computes in (its `runtimePrecision`), which the inference precision hint only asks for."""
    counts: dict[tuple[str, str], int] = {}
    for op in compiled.get_runtime_model().get_ops():
        info = op.get_rt_info()
        key = (info["layerType"].astype(str), info["runtimePrecision"].astype(str))
        counts[key] = counts.get(key, 0) + 1
    return counts


def _read(core: Any, path: Path) -> Any:
    try:
        return core.read_model(str(path))
    except Exception as error:  # OpenVINO raises RuntimeError subclasses of its own
        raise ValueError(f"cannot load ONNX model {path}: {error}") from error


def _metadata(model: Any) -> dict[str, str]:
    info = model.get_rt_info()  # the ONNX frontend puts metadata_props under "framework"
    framework = info["framework"] if "framework" in info else {}
    return {key: value.astype(str) for key, value in framework.items()}


def _input_shapes(model: Any) -> dict[str, tuple[int, ...]]:
    return {
        i.get_any_name(): tuple(d.get_length() if d.is_static else DYNAMIC for d in i.get_partial_shape())
        for i in model.inputs
    }


def describe(model_path: str | os.PathLike[str]) -> tuple[dict[str, str], dict[str, tuple[int, ...]], tuple[str, ...]]:
    """(metadata, input shapes, output names) of an ONNX model, read without compiling it."""
    import openvino as ov

    path = Path(model_path)
    if not path.is_file():
        raise FileNotFoundError(f"ONNX model {path} does not exist")
    model = _read(ov.Core(), path)
    return _metadata(model), _input_shapes(model), tuple(o.get_any_name() for o in model.outputs)


class OpenVinoBackend:
    """One compiled model with `concurrent_runs` CPU streams; each run takes an idle infer request (thread-safe)."""

    runtime = "openvino"

    def __init__(
        self,
        model_path: str | os.PathLike[str],
        precision: str,
        threads: int,
        concurrent_runs: int = 1,
        quantized: str | os.PathLike[str] | None = None,
    ) -> None:
        """`quantized`: the int8 model to run (default MODEL.int8.onnx beside it; the gate's islands search judges
        candidates kept elsewhere)."""
        import openvino as ov

        path = Path(model_path)
        if not path.is_file():
            raise FileNotFoundError(f"ONNX model {path} does not exist")
        if precision not in OV_PRECISION:
            raise ValueError(f"precision must be one of {sorted(OV_PRECISION)}, got {precision!r}")
        if precision == "bf16" and not openvino_supports_bf16():
            raise ValueError("this CPU has no bf16 support (needs avx512_bf16 or AMX); use precision fp32")
        core = ov.Core()
        self.path = path
        self.threads, self.concurrent_runs = int(threads), int(concurrent_runs)
        model = _read(core, path)
        self.metadata = _metadata(model)
        if quantized is not None and precision != "int8":
            raise ValueError(f"a quantized model is run as precision int8, not {precision!r}")
        if precision == "int8":
            quantized = Path(quantized) if quantized is not None else int8_model_path(path)
            if not quantized.is_file():
                raise FileNotFoundError(
                    f"precision int8 serves the quantized {quantized}, which does not exist (`rafd gate {path}` "
                    "writes it on a CPU with int8 units)"
                )
            model = _read(core, quantized)
        # the units the quantized file keeps in float32 (export/quantize.py records them in it); () for the rest
        self.islands: tuple[str, ...] = tuple(json.loads(_metadata(model).get(FLOAT32_ISLANDS_KEY, "[]")))
        self.input_shapes = _input_shapes(model)
        self.output_names = tuple(o.get_any_name() for o in model.outputs)
        # The threads are shared by the streams: each of `concurrent_runs` streams gets threads // streams.
        config = {
            "INFERENCE_PRECISION_HINT": OV_PRECISION[precision],
            "PERFORMANCE_HINT": "LATENCY" if self.concurrent_runs == 1 else "THROUGHPUT",
            "NUM_STREAMS": self.concurrent_runs,
            "INFERENCE_NUM_THREADS": self.threads * self.concurrent_runs,
        }
        # A graph with free axes is compiled for each set of shapes it is run with, as static shapes: OpenVINO's CPU
        # plugin runs a static shape 1.3-1.4x faster than the dynamic one (the shipped step at batch 1, one thread, AMD
        # EPYC Zen 4: fp32 15.9 against 22.4 ms), and a stream's views (a whole scan's tiles) always come in the same
        # number, so a service compiles a size or two: 1, and its whole-scan view's tile count. The shapes are the fed
        # arrays', input by input: a segment of a cut graph (bf16 islands) reads tensors whose free axis is not the
        # batch (the past frames stacked, 3 rows per window).
        self._core, self._model, self._config = core, model, config
        self._free = tuple(name for name, shape in self.input_shapes.items() if DYNAMIC in shape)
        self._compiled: dict[tuple[tuple[int, ...], ...], Any] = {}  # the free inputs' shapes -> compiled model
        self._idle: dict[tuple[tuple[int, ...], ...], queue.SimpleQueue[Any]] = {}  # idle InferRequests per compilation
        self._compiling = threading.Lock()
        self.single = self.compiled(shapes_at(self.input_shapes, 1))  # every free axis 1: a single run's
        compiled = self.single.get_property("INFERENCE_PRECISION_HINT").get_type_name()  # "bf16" / "f32"
        self.precision = "int8" if precision == "int8" else {"f32": "fp32"}.get(compiled, compiled)

    def _key(self, shapes: dict[str, tuple[int, ...]]) -> tuple[tuple[int, ...], ...]:
        return tuple(tuple(shapes[name]) for name in self._free)

    def compiled(self, shapes: dict[str, tuple[int, ...]]) -> Any:
        """The model compiled for inputs of these shapes, on first use (a graph without free axes: its own)."""
        key = self._key(shapes)
        with self._compiling:
            if key not in self._compiled:
                model = self._model
                if self._free:
                    model = model.clone()
                    model.reshape({name: list(shapes[name]) for name in self._free})
                self._compiled[key] = self._core.compile_model(model, "CPU", self._config)
                self._idle[key] = queue.SimpleQueue()
            return self._compiled[key]

    def run(self, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        shapes = {name: feeds[name].shape for name in self._free}
        compiled = self.compiled(shapes)
        idle = self._idle[self._key(shapes)]
        try:
            request = idle.get_nowait()
        except queue.Empty:
            request = compiled.create_infer_request()
        try:
            # share_outputs=False (the default): the arrays are copies, not views of the request's buffers
            results = request.infer(feeds)
            return {name: results[name] for name in self.output_names}
        finally:
            idle.put(request)
