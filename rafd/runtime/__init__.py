"""Torch-free streaming inference of exported RaFD step graphs (numpy + a runtime), shared by the service, the tests
and the tools. Backends one file each behind rafd.runtime.backend.Backend: onnxruntime fp32 (the reference) and
OpenVINO bf16/fp32/int8; carrying a stream's cache from step to step (rafd.runtime.streaming) is shared by all."""

from rafd.runtime.backend import PRECISIONS, RUNTIMES, Backend
from rafd.runtime.contract import METADATA_KEYS
from rafd.runtime.runners import OnnxRunner, OpenVinoRunner, create_runner, open_runner, supported_choices
from rafd.runtime.streaming import Runner, StepResult, StreamRunner, StreamState

__all__ = [
    "Backend",
    "METADATA_KEYS",
    "OnnxRunner",
    "OpenVinoRunner",
    "PRECISIONS",
    "RUNTIMES",
    "StepResult",
    "StreamRunner",
    "StreamState",
    "create_runner",
    "open_runner",
    "Runner",
    "supported_choices",
]
