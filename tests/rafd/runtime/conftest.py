"""Runtime tests run on the shipped model (any shipped model: nothing here depends on its outputs)."""

from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def shipped_onnx() -> Path:
    from rafd.assets import default_onnx

    try:
        return default_onnx()
    except FileNotFoundError as error:
        pytest.skip(f"the shipped model is not built: {error}")


@pytest.fixture(scope="session")
def gated_onnx(shipped_onnx, tmp_path_factory) -> Path:
    """The shipped model with a passed bf16 gate recorded in its metadata (as rafd-export --gate writes it)."""
    onnx = pytest.importorskip("onnx")
    proto = onnx.load(str(shipped_onnx))
    kept = [(p.key, p.value) for p in proto.metadata_props if p.key != "gate_bf16"]  # whatever the shipped verdict
    del proto.metadata_props[:]
    for key, value in kept + [("gate_bf16", "pass")]:
        proto.metadata_props.add(key=key, value=value)
    path = tmp_path_factory.mktemp("gated") / "gated.onnx"
    onnx.save(proto, str(path))
    return path
