"""int8 quantization (export/quantize.py): MODEL.int8.onnx beside the model, only the encoder's convolutions and
matrix products quantized (the sampling-position arithmetic, GridSample and the head stay float32), the model's
metadata carried over without its gate records; OpenVINO serves it as precision int8 with the float model's
metadata."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.utils.export_testing import make_checkpoint, small_config

onnx = pytest.importorskip("onnx")


@pytest.fixture(scope="module")
def quantized(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    from export.onnx_export import export_onnx
    from export.quantize import quantize_model

    folder = tmp_path_factory.mktemp("int8")
    model = folder / "m.onnx"
    export_onnx(make_checkpoint(folder / "m.pt", small_config(4)), model, verify=False)
    return model, quantize_model(model, sequences=1, frames=8)


def test_the_quantized_model_lies_beside_it_and_keeps_its_metadata_but_no_gate_record(quantized):
    from rafd.model_files import int8_model_path

    model, path = quantized
    assert path == int8_model_path(model) == model.with_name("m.int8.onnx")
    original = {p.key: p.value for p in onnx.load(str(model)).metadata_props}
    carried = {p.key: p.value for p in onnx.load(str(path)).metadata_props}
    assert {k: v for k, v in original.items() if not k.startswith("gate_")}.items() <= carried.items()
    assert not any(key.startswith("gate_") for key in carried)


def test_only_the_encoders_convolutions_and_matrix_products_are_quantized(quantized):
    _, path = quantized
    graph = onnx.load(str(path)).graph
    producers = {output: node for node in graph.node for output in node.output}
    constants = {tensor.name for tensor in graph.initializer}

    def int8_weights(node) -> bool:  # its weights are int8 constants, dequantized: it runs as an int8 kernel
        weights = producers.get(node.input[1]) if len(node.input) > 1 else None
        return weights is not None and weights.op_type == "DequantizeLinear" and weights.input[0] in constants

    quantized_ops = [n.name for n in graph.node if int8_weights(n)]
    assert quantized_ops and all(name.startswith("/encoder/") for name in quantized_ops), quantized_ops
    assert {n.op_type for n in graph.node if int8_weights(n)} <= {"Conv", "MatMul"}
    assert not any(int8_weights(n) for n in graph.node if n.op_type == "GridSample" or n.name.startswith("/head/"))


def test_openvino_serves_it_as_int8_with_the_float_models_metadata(quantized):
    pytest.importorskip("openvino")
    from rafd.runtime import OnnxRunner, open_runner

    model, _ = quantized
    int8 = open_runner(model, "openvino", "int8", threads=1)
    assert int8.precision == "int8" and int8.config == OnnxRunner(model, 1).config
    size = int8.config.input_size
    result, _ = int8.step(int8.new_state(), np.zeros((size, size), np.float32), np.zeros(3))
    assert result.frames_used == 1


def test_without_the_quantized_file_int8_says_how_to_make_it(tmp_path):
    pytest.importorskip("openvino")
    import shutil

    from rafd.assets import default_onnx
    from rafd.runtime import open_runner

    model = Path(shutil.copy(default_onnx(), tmp_path / "alone.onnx"))
    with pytest.raises(FileNotFoundError, match=r"alone\.int8\.onnx, which does not exist \(`rafd gate"):
        open_runner(model, "openvino", "int8", threads=1)
