"""onnxruntime CPU backend, float32: the reference path every other runtime is gated against."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from rafd.runtime.backend import DYNAMIC


class OrtBackend:
    """One InferenceSession; `run` is thread-safe (onnxruntime allows concurrent run() on one session)."""

    runtime = "onnxruntime"
    precision = "fp32"

    def __init__(
        self, model_path: str | os.PathLike[str], threads: int, concurrent_runs: int = 1, spinning: bool = True
    ) -> None:
        import onnxruntime as ort

        path = Path(model_path)
        if not path.is_file():
            raise FileNotFoundError(f"ONNX model {path} does not exist")
        self.path = path
        self.threads, self.concurrent_runs = int(threads), int(concurrent_runs)
        options = ort.SessionOptions()
        options.intra_op_num_threads = self.threads
        options.inter_op_num_threads = 1
        options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        if not spinning:  # idle pool threads sleep instead of spinning on cores other runs need
            options.add_session_config_entry("session.intra_op.allow_spinning", "0")
        try:
            self.session = ort.InferenceSession(str(path), sess_options=options, providers=["CPUExecutionProvider"])
        except Exception as error:  # onnxruntime raises its own exception types
            raise ValueError(f"cannot load ONNX model {path}: {error}") from error
        self.metadata: dict[str, str] = dict(self.session.get_modelmeta().custom_metadata_map)
        self.input_shapes = {
            i.name: tuple(d if isinstance(d, int) else DYNAMIC for d in i.shape) for i in self.session.get_inputs()
        }
        self.output_names = tuple(o.name for o in self.session.get_outputs())

    def run(self, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        return dict(zip(self.output_names, self.session.run(None, feeds)))
