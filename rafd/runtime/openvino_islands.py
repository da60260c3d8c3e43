"""OpenVINO bf16 with float32 islands: the model's segments (MODEL.bf16-islands/, export/islands.py) compiled one
each in its own precision, the islands in float32 and the rest in bf16, and run one after another (a float32 tensor
crosses every cut). Implements rafd.runtime.backend.Backend with precision "bf16"; the metadata, inputs and outputs
are the whole model's (MODEL.onnx: its gate record names the islands and the folder's digest)."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from rafd.model_files import ISLANDS_MANIFEST
from rafd.runtime.openvino_backend import OpenVinoBackend, describe


def read_manifest(folder: str | os.PathLike[str]) -> dict[str, Any]:
    """The islands folder's manifest ({"islands": [...], "segments": [{file, precision, inputs, outputs}]}); a
    ValueError saying what is wrong when it is missing or not one."""
    path = Path(folder, ISLANDS_MANIFEST)
    try:
        manifest = json.loads(path.read_text())
        for entry in manifest["segments"]:
            if entry["precision"] not in ("fp32", "bf16") or not isinstance(entry["file"], str):
                raise ValueError(f"segment {entry}")
            entry["inputs"], entry["outputs"] = list(entry["inputs"]), list(entry["outputs"])
        list(manifest["islands"])
    except (OSError, ValueError, KeyError, TypeError) as error:
        raise ValueError(f"{path} is not a bf16-islands manifest: {error}") from error
    return dict(manifest)


class OpenVinoIslandsBackend:
    """The segments of one model, each an OpenVinoBackend in its precision with the same threads and concurrent runs;
    `run` chains them."""

    runtime = "openvino"
    precision = "bf16"

    def __init__(
        self,
        model_path: str | os.PathLike[str],
        folder: str | os.PathLike[str],
        threads: int,
        concurrent_runs: int = 1,
    ) -> None:
        self.path = Path(model_path)
        self.folder = Path(folder)
        self.metadata, self.input_shapes, self.output_names = describe(self.path)
        manifest = read_manifest(self.folder)
        self.islands = tuple(manifest["islands"])
        self.threads, self.concurrent_runs = int(threads), int(concurrent_runs)
        self.segments = [
            (
                entry["inputs"],
                OpenVinoBackend(self.folder / entry["file"], entry["precision"], threads, concurrent_runs),
            )
            for entry in manifest["segments"]
        ]
        # Every value a segment reads must be a graph input or an earlier segment's output, and the chain must end
        # with every graph output: a folder cut from another graph fails here, not in the middle of a run.
        known = set(self.input_shapes)
        for inputs, segment in self.segments:
            missing = set(inputs) - known
            if missing:
                raise ValueError(f"{self.folder}: segment {segment.path.name} reads {sorted(missing)}, never produced")
            known |= set(segment.output_names)
        if not set(self.output_names) <= known:
            raise ValueError(f"{self.folder}: no segment produces {sorted(set(self.output_names) - known)}")

    def run(self, feeds: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        values = dict(feeds)
        for inputs, segment in self.segments:
            values.update(segment.run({name: values[name] for name in inputs}))
        return {name: values[name] for name in self.output_names}
