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
    """The shipped model with a passed bf16 gate recorded in its metadata (as rafd-export --gate writes it: the
    verdict and its figures, enough windows and detections for the service to consider it) and no other record."""
    import json

    onnx = pytest.importorskip("onnx")
    proto = onnx.load(str(shipped_onnx))
    kept = [(p.key, p.value) for p in proto.metadata_props if not p.key.startswith("gate_")]  # any verdict
    del proto.metadata_props[:]
    pooled = {"frames": 699, "reference_detections": 1909, "candidate_detections": 1925}
    figures = json.dumps({"candidate": "openvino/bf16", "reference": "onnxruntime/fp32", "figures": {"all": pooled}})
    for key, value in kept + [("gate_bf16", "pass"), ("gate_bf16_figures", figures)]:
        proto.metadata_props.add(key=key, value=value)
    path = tmp_path_factory.mktemp("gated") / "gated.onnx"
    onnx.save(proto, str(path))
    return path


@pytest.fixture(scope="session")
def ungated_onnx(shipped_onnx, tmp_path_factory) -> Path:
    """The shipped model without any gate record (a model a user exported without --gate): reduced precisions
    are never chosen automatically for it."""
    onnx = pytest.importorskip("onnx")
    proto = onnx.load(str(shipped_onnx))
    kept = [(p.key, p.value) for p in proto.metadata_props if not p.key.startswith("gate_")]
    del proto.metadata_props[:]
    for key, value in kept:
        proto.metadata_props.add(key=key, value=value)
    path = tmp_path_factory.mktemp("ungated") / "ungated.onnx"
    onnx.save(proto, str(path))
    return path
