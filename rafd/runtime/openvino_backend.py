"""OpenVINO CPU backend (the native `openvino` package), bf16 or float32.

Chosen over onnxruntime's OpenVINO execution provider by measurement (same bf16 speed on the paper step graph
here, see docs/performance.md), and because `onnxruntime-openvino` installs a second `onnxruntime`
module over the reference one. OpenVINO reads the ONNX file directly, metadata included (rt_info "framework").
bf16 runs on avx512_bf16 (and AMX where present); OpenVINO keeps precision-sensitive parts in float32 itself.
"""

from __future__ import annotations

import os
import queue
from pathlib import Path
from typing import Any

import numpy as np

from rafd.runtime.backend import DYNAMIC

OV_PRECISION = {"fp32": "f32", "bf16": "bf16"}


def openvino_supports_bf16() -> bool:
    """Whether OpenVINO's CPU plugin can compute in bf16 on this CPU (False when openvino is not installed)."""
    try:
        import openvino as ov
    except ImportError:
        return False
    return "BF16" in ov.Core().get_property("CPU", "OPTIMIZATION_CAPABILITIES")


class OpenVinoBackend:
    """One compiled model with `concurrent_runs` CPU streams; each run takes an idle infer request (thread-safe)."""

    runtime = "openvino"

    def __init__(
        self, model_path: str | os.PathLike[str], precision: str, threads: int, concurrent_runs: int = 1
    ) -> None:
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
        try:
            model = core.read_model(str(path))
        except Exception as error:  # OpenVINO raises RuntimeError subclasses of its own
            raise ValueError(f"cannot load ONNX model {path}: {error}") from error
        info = model.get_rt_info()  # the ONNX frontend puts metadata_props under "framework"
        framework = info["framework"] if "framework" in info else {}
        self.metadata = {key: value.astype(str) for key, value in framework.items()}
        self.input_shapes = {
            i.get_any_name(): tuple(d.get_length() if d.is_static else DYNAMIC for d in i.get_partial_shape())
            for i in model.inputs
        }
        self.output_names = tuple(o.get_any_name() for o in model.outputs)
        # The threads are shared by the streams: each of `concurrent_runs` streams gets threads // streams.
        config = {
            "INFERENCE_PRECISION_HINT": OV_PRECISION[precision],
            "PERFORMANCE_HINT": "LATENCY" if self.concurrent_runs == 1 else "THROUGHPUT",
            "NUM_STREAMS": self.concurrent_runs,
            "INFERENCE_NUM_THREADS": self.threads * self.concurrent_runs,
        }
        self.compiled = core.compile_model(model, "CPU", config)
        compiled = self.compiled.get_property("INFERENCE_PRECISION_HINT").get_type_name()  # "bf16" / "f32"
        self.precision = {"f32": "fp32"}.get(compiled, compiled)
        self._idle: queue.SimpleQueue[Any] = queue.SimpleQueue()  # openvino InferRequests (untyped library)

    def run(self, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        try:
            request = self._idle.get_nowait()
        except queue.Empty:
            request = self.compiled.create_infer_request()
        try:
            # share_outputs=False (the default): the arrays are copies, not views of the request's buffers
            results = request.infer(feeds)
            return {name: results[name] for name in self.output_names}
        finally:
            self._idle.put(request)
