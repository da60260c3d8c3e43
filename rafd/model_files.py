"""What kind of model file a path holds, from its first bytes (torch-free): a checkpoint (a torch file: a zip
archive, or a legacy pickle) or an ONNX model (a protobuf ModelProto). Lets every command say "this is an ONNX
model, not a checkpoint" (and the reverse) instead of passing on a library's parse error."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Literal

FileKind = Literal["checkpoint", "onnx", "unknown"]
# ModelProto fields that follow ir_version (field 1, varint, written first): producer_name, producer_version,
# domain, model_version, doc_string, graph, opset_import (protobuf tags of fields 2-8).
_ONNX_SECOND_FIELDS = frozenset({0x12, 0x1A, 0x22, 0x28, 0x32, 0x3A, 0x42})


def file_kind(path: str | os.PathLike[str]) -> FileKind:
    """ "checkpoint" (zip or pickle: what torch.save writes), "onnx" (an ONNX ModelProto) or "unknown"."""
    try:
        with open(path, "rb") as file:
            head = file.read(8)
    except OSError:
        return "unknown"
    if head[:4] == b"PK\x03\x04" or (len(head) > 1 and head[0] == 0x80 and 2 <= head[1] <= 5):
        return "checkpoint"
    # ir_version (tag 0x08) as a one-byte varint (ONNX IR versions 1-13), then the next field's tag
    if len(head) > 2 and head[0] == 0x08 and 1 <= head[1] < 0x80 and head[2] in _ONNX_SECOND_FIELDS:
        return "onnx"
    return "unknown"


def onnx_given_for_checkpoint(path: str | os.PathLike[str]) -> str | None:
    """The message when `path` is an ONNX model where a checkpoint is expected, else None."""
    if file_kind(path) != "onnx":
        return None
    return (
        f"{path} is an ONNX model, not a checkpoint: this command takes the checkpoint (.pt) that `rafd train` "
        f"writes; an ONNX model is what `rafd serve --model {Path(path).name}` serves"
    )


def checkpoint_given_for_onnx(path: str | os.PathLike[str]) -> str | None:
    """The message when `path` is a PyTorch checkpoint where an ONNX model is expected, else None."""
    if file_kind(path) != "checkpoint":
        return None
    return (
        f"{path} is a PyTorch checkpoint, not an ONNX model: export it first "
        f"(`rafd export {Path(path).name} --out model.onnx`), then serve the ONNX file"
    )


def int8_model_path(path: str | os.PathLike[str]) -> Path:
    """Where the int8 (quantized) form of an ONNX model lives: beside it, MODEL.int8.onnx (`rafd gate` writes it on a
    CPU with int8 units; the service serves it only where its accuracy gate, recorded in MODEL.onnx, passed)."""
    model = Path(path)
    return model.with_name(model.name.removesuffix(".onnx") + ".int8.onnx")


# The metadata entry of a quantized model naming the units it keeps in float32 (a JSON list; export/quantize.py).
FLOAT32_ISLANDS_KEY = "float32_islands"


def file_sha256(path: str | os.PathLike[str]) -> str:
    """The hex sha256 of a file's bytes (a checkpoint, a model), read in 1 MiB blocks."""
    digest = hashlib.sha256()
    with open(path, "rb") as file:
        for block in iter(lambda: file.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


# The manifest of a bf16-with-float32-islands folder (export/islands.py writes it, rafd.runtime chains its segments).
ISLANDS_MANIFEST = "segments.json"


def islands_dir(path: str | os.PathLike[str]) -> Path:
    """Where the bf16-with-float32-islands form of an ONNX model lives: beside it, MODEL.bf16-islands/ (segment_K.onnx
    and ISLANDS_MANIFEST; `rafd gate` writes it where plain bf16 fails its gate and an islands set passes)."""
    model = Path(path)
    return model.with_name(model.name.removesuffix(".onnx") + ".bf16-islands")


def islands_sha256(folder: str | os.PathLike[str]) -> str:
    """One sha256 over an islands folder's manifest and every segment it names, in the manifest's order: the gate
    record names the folder it judged by it."""
    import json

    digest = hashlib.sha256()
    manifest = Path(folder, ISLANDS_MANIFEST)
    digest.update(manifest.read_bytes())
    for entry in json.loads(manifest.read_text())["segments"]:
        digest.update(file_sha256(Path(folder, entry["file"])).encode())
    return digest.hexdigest()
