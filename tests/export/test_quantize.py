"""int8 quantization (export/quantize.py): MODEL.int8.onnx beside the model, every convolution and matrix product
quantized but those in the float32 islands (the sampling-position arithmetic, GridSample and the decode are never
quantized), the islands named in the file, the model's metadata carried over without its gate records; OpenVINO
serves it as precision int8 with the float model's metadata and reports its islands."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tests.utils.export_testing import make_checkpoint, small_config

onnx = pytest.importorskip("onnx")


ISLANDS = ("/head/", "/flow_match/")  # kept float32 in the quantized copy the tests read


@pytest.fixture(scope="module")
def quantized(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    from export.onnx_export import export_onnx
    from export.quantize import calibrate, quantize_model

    folder = tmp_path_factory.mktemp("int8")
    model = folder / "m.onnx"
    export_onnx(make_checkpoint(folder / "m.pt", small_config(4)), model, verify=False)
    calibration = calibrate(model, sequences=1, frames=8)
    return model, quantize_model(model, islands=ISLANDS, calibration=calibration)


def test_the_quantized_model_lies_beside_it_and_keeps_its_metadata_but_no_gate_record(quantized):
    from rafd.model_files import FLOAT32_ISLANDS_KEY, int8_model_path

    model, path = quantized
    assert path == int8_model_path(model) == model.with_name("m.int8.onnx")
    original = {p.key: p.value for p in onnx.load(str(model)).metadata_props}
    carried = {p.key: p.value for p in onnx.load(str(path)).metadata_props}
    assert {k: v for k, v in original.items() if not k.startswith("gate_")}.items() <= carried.items()
    assert not any(key.startswith("gate_") for key in carried)
    assert json.loads(carried[FLOAT32_ISLANDS_KEY]) == list(ISLANDS)


def _int8_kernels(path: Path) -> list[str]:
    """The names of the nodes that run as int8 kernels: both inputs dequantized, the weights from a constant."""
    graph = onnx.load(str(path)).graph
    producers = {output: node for node in graph.node for output in node.output}
    constants = {tensor.name for tensor in graph.initializer}

    def dequantized(value: str) -> bool:
        return value in producers and producers[value].op_type == "DequantizeLinear"

    def from_constant(value: str) -> bool:  # through QuantizeLinear / DequantizeLinear to an initializer
        node = producers.get(value)
        while node is not None and node.op_type in ("QuantizeLinear", "DequantizeLinear"):
            value, node = node.input[0], producers.get(node.input[0])
        return value in constants

    return [
        n.name
        for n in graph.node
        if len(n.input) > 1 and dequantized(n.input[0]) and dequantized(n.input[1]) and from_constant(n.input[1])
    ]


def test_every_matrix_operation_outside_the_islands_is_quantized_and_nothing_else(quantized):
    from export.islands import constant_values, in_scope

    model, path = quantized
    proto = onnx.load(str(model))
    weights = constant_values(proto) | {t.name for t in proto.graph.initializer}
    # the matrix operations with constant weights (a product of two activations has none to read as int8 here)
    weighted = {n.name for n in proto.graph.node if n.op_type in ("Conv", "MatMul") and n.input[1] in weights}
    outside = {name for name in weighted if not any(in_scope(name, island) for island in ISLANDS)}
    kernels = set(_int8_kernels(path))
    assert kernels == outside and weighted - outside, sorted(kernels ^ outside)
    assert any(name.startswith("/encoder/") for name in kernels) and any(name.startswith("/flow_") for name in kernels)


def test_one_calibration_quantizes_any_set_as_a_fresh_one_would_and_only_its_own_model(quantized, tmp_path):
    """The search quantizes many sets from one calibration: the same file as one calibrated afresh; a set that leaves
    nothing to quantize, or another model, is refused."""
    import shutil

    from export.quantize import calibrate, quantize_model

    model, path = quantized
    fresh = calibrate(model, sequences=1, frames=8)
    again = quantize_model(model, tmp_path / "again.int8.onnx", ISLANDS, fresh)
    assert onnx.load(str(again)) == onnx.load(str(path))
    with pytest.raises(ValueError, match="nothing left to quantize"):
        quantize_model(model, tmp_path / "none.int8.onnx", ("/",), fresh)
    other = shutil.copy(model, tmp_path / "other.onnx")
    with pytest.raises(ValueError, match="the calibration is .*m.onnx's, not .*other.onnx's"):
        quantize_model(other, calibration=fresh)


def test_openvino_serves_it_as_int8_with_the_float_models_metadata(quantized):
    pytest.importorskip("openvino")
    from rafd.runtime import OnnxRunner, open_runner

    model, _ = quantized
    int8 = open_runner(model, "openvino", "int8", threads=1)
    assert int8.precision == "int8" and int8.config == OnnxRunner(model, 1).config
    assert int8.islands == ISLANDS and int8.describe()["float32_islands"] == list(ISLANDS)
    size = int8.config.input_size
    result, _ = int8.step(int8.new_state(), np.zeros((1, size, size), np.float32), np.zeros((1, 3)))
    assert result.frames_used == 1


def test_without_the_quantized_file_int8_says_how_to_make_it(tmp_path):
    pytest.importorskip("openvino")
    import shutil

    from rafd.assets import default_onnx
    from rafd.runtime import open_runner

    model = Path(shutil.copy(default_onnx(), tmp_path / "alone.onnx"))
    with pytest.raises(FileNotFoundError, match=r"alone\.int8\.onnx, which does not exist \(`rafd gate"):
        open_runner(model, "openvino", "int8", threads=1)


@pytest.mark.parametrize("which", ["small", "shipped"])
def test_the_graph_prepared_for_quantization_has_no_no_op_nodes_and_computes_the_same(quantized, which):
    """The exporter's Identity nodes (a shared weight: the small model) and Casts to a value's own type (the shipped
    model's output new_cache.flow_features is one, which NNCF 3.4's own pass fails on) go; every node keeps its
    name and the graph its outputs and results."""
    import onnxruntime as ort

    from export.quantize import prepared_for_quantization
    from rafd.assets import default_onnx

    proto = onnx.load(str(quantized[0] if which == "small" else default_onnx()))
    prepared = prepared_for_quantization(proto)
    no_op = "Identity" if which == "small" else "Cast"
    producer = [{out: n.op_type for n in p.graph.node for out in n.output} for p in (proto, prepared)]
    assert any(n.op_type == no_op for n in proto.graph.node) and not any(
        n.op_type == "Identity" for n in prepared.graph.node
    )
    if which == "shipped":
        cached = "new_cache.flow_features"
        assert producer[0][cached] == "Cast" and producer[1][cached] == "Conv"
    assert {n.name for n in prepared.graph.node} <= {n.name for n in proto.graph.node}
    assert [o.name for o in prepared.graph.output] == [o.name for o in proto.graph.output]
    sessions = [
        ort.InferenceSession(p.SerializeToString(), providers=["CPUExecutionProvider"]) for p in (proto, prepared)
    ]
    rng = np.random.default_rng(2)
    feeds = {
        i.name: rng.random([1 if not isinstance(d, int) else d for d in i.shape], dtype=np.float32) * 0.3
        for i in sessions[0].get_inputs()
    }
    for before, after in zip(*(s.run(None, feeds) for s in sessions)):
        np.testing.assert_allclose(after, before, rtol=1e-5, atol=1e-6)
