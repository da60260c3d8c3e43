"""A model whose bf16 gate record passed with float32 islands, and their folder beside it (as `rafd gate` leaves it
after an islands search), for the runtime and service tests."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from export.islands import write_islands
from rafd.model_files import islands_sha256


def islands_record(islands: tuple[str, ...], digest: str | None) -> dict[str, str]:
    """A passed bf16 gate record on enough evidence naming `islands` and the folder digest (None: no digest)."""
    pooled = {"frames": 699, "reference_detections": 1909, "candidate_detections": 1909}
    figures = {"candidate": "openvino/bf16", "figures": {"all": pooled}, "islands": list(islands)}
    if digest is not None:
        figures["islands_sha256"] = digest
    return {"gate_bf16": "pass", "gate_bf16_figures": json.dumps(figures)}


def make_islands_model(ungated: Path, target: Path, islands: tuple[str, ...]) -> Path:
    """Copy the ungated model `ungated` to `target`, cut its islands beside it and record them as passed."""
    import onnx

    shutil.copy(ungated, target)
    folder = write_islands(target, islands)
    proto = onnx.load(str(target))
    for key, value in islands_record(islands, islands_sha256(folder)).items():
        proto.metadata_props.add(key=key, value=value)
    onnx.save(proto, str(target))
    return target
