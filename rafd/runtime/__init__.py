"""Torch-free streaming inference of exported RaFD graphs (numpy + a runtime), shared by the service, the tests
and the tools. Backends one file each behind rafd.runtime.backend.Backend: onnxruntime fp32 (the reference) and
OpenVINO bf16/fp32; the streaming and warm-up logic (rafd.runtime.streaming) is shared by all of them."""

from rafd.runtime.backend import PRECISIONS, RUNTIMES, Backend
from rafd.runtime.contract import FORMS, METADATA_KEYS, graph_inputs, graph_outputs
from rafd.runtime.runners import OnnxRunner, OpenVinoRunner, create_runner, open_runner, supported_choices
from rafd.runtime.streaming import (
    Runner,
    StepResult,
    StreamRunner,
    StreamState,
    poses_in_newest_frame,
    window_from_history,
)

__all__ = [
    "Backend",
    "FORMS",
    "METADATA_KEYS",
    "OnnxRunner",
    "OpenVinoRunner",
    "PRECISIONS",
    "RUNTIMES",
    "StepResult",
    "StreamRunner",
    "StreamState",
    "create_runner",
    "graph_inputs",
    "graph_outputs",
    "open_runner",
    "poses_in_newest_frame",
    "Runner",
    "supported_choices",
    "window_from_history",
]
