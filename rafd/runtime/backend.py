"""The one interface every runtime backend implements (one file per backend), and what they share."""

from __future__ import annotations

from typing import Protocol

import numpy as np

RUNTIMES = ("onnxruntime", "openvino")
DYNAMIC = -1  # an input dimension the graph leaves free (the batch axis of a batchable export)
PRECISIONS = ("fp32", "bf16", "int8")  # int8: the quantized MODEL.int8.onnx (OpenVINO)


def shapes_at(input_shapes: dict[str, tuple[int, ...]], batch: int) -> dict[str, tuple[int, ...]]:
    """The graph's input shapes with every free (DYNAMIC) dimension set to `batch`."""
    return {name: tuple(batch if d == DYNAMIC else d for d in shape) for name, shape in input_shapes.items()}


class Backend(Protocol):
    """A compiled RaFD graph: thread-safe `run`, static input shapes, the export's metadata."""

    runtime: str  # one of RUNTIMES
    precision: str  # one of PRECISIONS: what the backend really computes in, read back after compilation
    threads: int  # threads one run uses
    concurrent_runs: int  # runs the backend is prepared to execute at once
    metadata: dict[str, str]  # the ONNX metadata_props (rafd.runtime.contract.METADATA_KEYS and more)
    input_shapes: dict[str, tuple[int, ...]]  # graph inputs in graph order -> shapes (DYNAMIC where left free)
    output_names: tuple[str, ...]  # graph outputs in graph order

    def run(self, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """One inference -> {output name: array owned by the caller}."""
        ...
