"""bf16's float32 islands as graph segments (export/islands.py): the search's units, every node in one segment of its
precision, the segments chained equal to the whole graph, the folder and its digest."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from export.islands import (
    MATRIX_OPS,
    constant_values,
    in_scope,
    module_scopes,
    search_units,
    segment_models,
    split,
    unit_of,
    write_islands,
)
from rafd.model_files import ISLANDS_MANIFEST, islands_dir, islands_sha256

onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")

SCOPES = ["/encoder/", "/flow_encode/", "/flow_match/", "/propagation/", "/head/"]


@pytest.fixture(scope="module")
def shipped(tmp_path_factory):
    from rafd.assets import default_onnx

    try:
        path = default_onnx()
    except FileNotFoundError as error:
        pytest.skip(f"the shipped model is not built: {error}")
    return shutil.copy(path, tmp_path_factory.mktemp("islands") / "model.onnx")


@pytest.fixture(scope="module")
def proto(shipped):
    return onnx.load(str(shipped))


def _feeds(session):
    rng = np.random.default_rng(0)
    shape = lambda i: [d if isinstance(d, int) else 1 for d in i.shape]  # noqa: E731 (the free batch axis: 1)
    return {i.name: rng.random(shape(i), dtype=np.float32) for i in session.get_inputs()}


UNITS = ["/flow_match/*", "/head/heatmap/"]  # a scope's own nodes and a module under a scope


def test_an_island_is_a_subtree_or_a_scopes_own_nodes():
    assert in_scope("/flow/match/MatMul", "/flow/") and in_scope("/flow/Mul_3", "/flow/")
    assert in_scope("/flow/Mul_3", "/flow/*") and not in_scope("/flow/match/MatMul", "/flow/*")
    assert in_scope("/Gather_2", "/*") and not in_scope("/flow/Mul_3", "/*")
    assert not in_scope("/flow_1/Mul", "/flow/") and not in_scope("Constant_7", "/*")
    assert [unit_of(n) for n in ("/encoder/backbone/layer1/conv/Conv", "/flow/Mul", "/Gather_2", "Identity_3")] == [
        "/encoder/backbone/",
        "/flow/*",
        "/*",
        None,
    ]


def test_the_search_units_part_the_graph_by_matrix_work(proto):
    assert module_scopes(proto) == SCOPES
    matrix_free, matrix = search_units(proto)
    assert matrix_free == ["/encoder/normalise/", "/*", "/flow_encode/*", "/propagation/*", "/head/*"]
    assert matrix[:3] == ["/encoder/backbone/", "/encoder/neck/", "/encoder/enhancement/"]
    assert matrix[3:5] == ["/flow_encode/encoder/", "/flow_match/*"]
    constant = constant_values(proto)
    for node in proto.graph.node:
        if set(node.output) <= constant:
            continue
        (unit,) = [u for u in matrix_free + matrix if in_scope(node.name, u)]  # every node in exactly one unit
        assert unit in matrix or node.op_type not in MATRIX_OPS
    assert all(any(in_scope(n.name, u) and n.op_type in MATRIX_OPS for n in proto.graph.node) for u in matrix)


@pytest.mark.parametrize(
    "islands, precisions",
    [
        (("/propagation/", "/head/"), ["bf16", "fp32"]),
        (("/flow_match/",), ["bf16", "fp32", "bf16"]),
        (("/encoder/", "/head/"), ["fp32", "bf16", "fp32"]),
        (tuple(UNITS), ["bf16", "fp32", "bf16", "fp32", "bf16"]),
    ],
)
def test_every_node_lies_in_one_segment_of_its_precision(proto, islands, precisions):
    segments = split(proto, islands)
    assert [s.precision for s in segments] == precisions
    placed = [i for s in segments for i in s.nodes]
    constant = constant_values(proto)
    not_constant = [i for i, node in enumerate(proto.graph.node) if not set(node.output) <= constant]
    assert sorted(placed) == not_constant  # each once
    for segment in segments:
        for i in segment.nodes:
            inside = any(in_scope(proto.graph.node[i].name, island) for island in islands)
            assert inside == (segment.precision == "fp32")
    produced = {name for s in segments for name in s.outputs}
    assert {o.name for o in proto.graph.output} <= produced


@pytest.mark.parametrize(
    "islands", [("/propagation/", "/head/"), ("/flow_match/",), ("/encoder/", "/head/"), tuple(UNITS)]
)
def test_the_segments_chained_give_the_whole_graphs_outputs(shipped, proto, islands):
    whole = ort.InferenceSession(str(shipped), providers=["CPUExecutionProvider"])
    feeds = _feeds(whole)
    expected = dict(zip([o.name for o in whole.get_outputs()], whole.run(None, feeds)))
    segments = split(proto, islands)
    values = dict(feeds)
    for segment, model in zip(segments, segment_models(proto, segments)):
        assert [i.name for i in model.graph.input] == list(segment.inputs)
        session = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
        values.update(
            zip([o.name for o in session.get_outputs()], session.run(None, {n: values[n] for n in segment.inputs}))
        )
    for name, array in expected.items():
        np.testing.assert_allclose(values[name], array, rtol=0, atol=1e-5, err_msg=name)


def test_an_unknown_scope_is_refused_naming_the_graphs_scopes(proto):
    with pytest.raises(ValueError, match=r"no node in \['/neck/'\].*'/encoder/'"):
        split(proto, ("/neck/",))
    with pytest.raises(ValueError, match=r"no node in \['/encoder/\*'\]"):  # the encoder has no nodes of its own
        split(proto, ("/encoder/*",))
    deeper = sorted({"/".join(n.name.split("/")[:3]) + "/" for n in proto.graph.node if n.name.startswith("/encoder/")})
    segments = split(proto, (deeper[0],))  # a deeper scope is an island too
    assert "fp32" in [s.precision for s in segments]


def test_the_folder_holds_the_segments_and_its_digest_follows_them(shipped):
    folder = write_islands(shipped, ("/propagation/", "/head/"))
    assert folder == islands_dir(shipped) and folder.name == "model.bf16-islands"
    assert folder.stat().st_mode & 0o777 == 0o755  # readable by a service running as another user
    manifest = json.loads((folder / ISLANDS_MANIFEST).read_text())
    assert manifest["islands"] == ["/propagation/", "/head/"]
    assert [(e["file"], e["precision"]) for e in manifest["segments"]] == [
        ("segment_0.onnx", "bf16"),
        ("segment_1.onnx", "fp32"),
    ]
    assert sorted(p.name for p in folder.iterdir()) == sorted([ISLANDS_MANIFEST, "segment_0.onnx", "segment_1.onnx"])
    digest = islands_sha256(folder)
    assert digest == islands_sha256(folder)  # the same bytes, the same digest
    with open(folder / "segment_1.onnx", "ab") as file:  # a segment changed after the gate
        file.write(b"\0")
    assert islands_sha256(folder) != digest
    again = write_islands(shipped, ("/flow_match/",))  # a new set replaces the folder whole
    assert json.loads((again / ISLANDS_MANIFEST).read_text())["islands"] == ["/flow_match/"]
    assert sorted(p.name for p in again.iterdir()) == sorted(
        [ISLANDS_MANIFEST] + [f"segment_{k}.onnx" for k in range(3)]
    )
    assert not [p for p in again.parent.iterdir() if p.name.startswith(".")]  # no temporary folder left


def test_a_static_batch_graphs_segments_have_every_cut_shape_and_compile_in_openvino(tmp_path):
    """onnx's shape inference leaves some cut values' dimensions unknown (the paper network's static-batch step);
    OpenVINO's batch-1 compilation needs them, so the cuts' shapes are measured. Each segment of a split with cuts
    both ways compiles (fp32: any CPU) and the chain equals the whole graph."""
    pytest.importorskip("torch")
    pytest.importorskip("openvino", reason="the serve extra installs openvino")
    from export.onnx_export import export_onnx
    from rafd.runtime.openvino_backend import OpenVinoBackend
    from tests.utils.export_testing import make_checkpoint, small_config

    model = tmp_path / "static.onnx"
    export_onnx(
        make_checkpoint(tmp_path / "m.pt", small_config(4)), model, batch="static", verify=False, log=lambda _: None
    )
    whole = ort.InferenceSession(str(model), providers=["CPUExecutionProvider"])
    feeds = _feeds(whole)
    expected = dict(zip([o.name for o in whole.get_outputs()], whole.run(None, feeds)))
    for scope in ("/flow_match/",):  # bf16, fp32, bf16: cuts both ways (every single scope: 17 s, not 5)
        folder = write_islands(model, (scope,))
        manifest = json.loads((folder / ISLANDS_MANIFEST).read_text())
        values = dict(feeds)
        for entry in manifest["segments"]:
            segment = onnx.load(str(folder / entry["file"]))
            for value in segment.graph.input:
                assert all(d.HasField("dim_value") for d in value.type.tensor_type.shape.dim), (scope, value.name)
            backend = OpenVinoBackend(folder / entry["file"], "fp32", threads=1)
            values.update(backend.run({name: values[name] for name in entry["inputs"]}))
        for name, array in expected.items():
            np.testing.assert_allclose(values[name], array, rtol=0, atol=1e-4, err_msg=f"{scope} {name}")
