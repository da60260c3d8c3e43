"""The OpenVINO backend behind the one runner interface: same graph contract and metadata as onnxruntime, fp32
results equal to onnxruntime's, bf16 really in effect, thread-safe concurrent runs."""

from __future__ import annotations

import concurrent.futures

import numpy as np
import pytest

from rafd.runtime import OnnxRunner, OpenVinoRunner

pytest.importorskip("openvino", reason="the serve extra installs openvino")
from rafd.runtime.backend import DYNAMIC, shapes_at  # noqa: E402
from rafd.runtime.openvino_backend import openvino_supports_bf16  # noqa: E402


def _sequence(cfg, n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    frames = (rng.random((n, cfg.input_size, cfg.input_size)) * 0.4).astype(np.float32)
    poses = np.cumsum(rng.normal(0.0, 1.0, (n, 3)) * [1.0, 1.5, 0.03], axis=0)
    return frames, poses


def _stream(runner, frames, poses):
    state, results = runner.new_state(), []
    for frame, pose in zip(frames, poses):
        result, state = runner.step(state, frame[None], pose[None])
        results.append(result)
    return results


def test_backends_share_the_interface_and_metadata(shipped_onnx):
    ort, ov = OnnxRunner(shipped_onnx, threads=1), OpenVinoRunner(shipped_onnx, "fp32", threads=1)
    assert (ort.runtime, ort.precision, ov.runtime, ov.precision) == ("onnxruntime", "fp32", "openvino", "fp32")
    assert ov.metadata == ort.metadata and ov.config == ort.config and ov.cache_names == ort.cache_names
    assert ov.backend.input_shapes == ort.backend.input_shapes
    assert ov.backend.output_names == ort.backend.output_names
    assert ov.describe() == {
        "runtime": "openvino",
        "precision": "fp32",
        "threads": 1,
        "concurrent_runs": 1,
        "threads_per_concurrent_run": 1,
        "selection_ms_per_run": {},
        "float32_islands": [],
    }


def test_openvino_fp32_streams_like_onnxruntime(shipped_onnx):
    ort, ov = OnnxRunner(shipped_onnx, threads=1), OpenVinoRunner(shipped_onnx, "fp32", threads=1)
    frames, poses = _sequence(ort.config, 6)
    for a, b in zip(_stream(ort, frames, poses), _stream(ov, frames, poses)):
        assert a.frames_used == b.frames_used
        np.testing.assert_allclose(b.heatmap, a.heatmap, atol=1e-4, rtol=1e-4)
        np.testing.assert_allclose(b.flow, a.flow, atol=1e-4, rtol=1e-4)
        np.testing.assert_allclose(np.sort(b.scores), np.sort(a.scores), atol=1e-5)


@pytest.mark.skipif(not openvino_supports_bf16(), reason="this CPU has no bf16 (avx512_bf16 or AMX)")
def test_bf16_is_really_bf16_and_close(shipped_onnx):
    ort, bf16 = OnnxRunner(shipped_onnx, threads=1), OpenVinoRunner(shipped_onnx, "bf16", threads=1)
    assert bf16.precision == "bf16"
    frames, poses = _sequence(ort.config, 5, seed=1)
    differences = [
        np.abs(a.heatmap - b.heatmap).max() for a, b in zip(_stream(ort, frames, poses), _stream(bf16, frames, poses))
    ]
    # bf16 keeps 8 significant bits: the logits move, but stay in the same range (the accuracy gate judges more)
    assert 1e-4 < max(differences) < 5.0, differences


def test_bf16_refused_where_the_cpu_lacks_it(shipped_onnx, monkeypatch):
    from rafd.runtime import openvino_backend, runners

    monkeypatch.setattr(openvino_backend, "openvino_supports_bf16", lambda: False)
    with pytest.raises(ValueError, match="no bf16"):
        OpenVinoRunner(shipped_onnx, "bf16", threads=1)
    assert ("openvino", "bf16") not in runners.supported_choices()


def test_concurrent_runs_give_the_serial_results(shipped_onnx):
    runner = OpenVinoRunner(shipped_onnx, "fp32", threads=1, concurrent_runs=2)
    rng = np.random.default_rng(3)
    shapes = shapes_at(runner.backend.input_shapes, 1)  # the free batch axis fed as one stream
    feeds = [{name: rng.random(shape, dtype=np.float32) for name, shape in shapes.items()} for _ in range(6)]
    serial = [runner.run(f) for f in feeds]
    with concurrent.futures.ThreadPoolExecutor(4) as pool:
        parallel = list(pool.map(runner.run, feeds))
    for a, b in zip(serial, parallel):
        for name in a:
            np.testing.assert_array_equal(a[name], b[name])


def test_a_batched_run_compiles_its_batch_size_on_first_use_and_agrees_with_single_runs(shipped_onnx):
    """Single runs take the batch-1 compilation; each other batch size is compiled static by its first run only (a
    service that never batches never pays for it), and its rows equal the single runs'."""
    runner = OpenVinoRunner(shipped_onnx, "fp32", threads=1)
    backend = runner.backend
    rng = np.random.default_rng(5)
    shapes = shapes_at(backend.input_shapes, 1)
    assert any(DYNAMIC in s for s in backend.input_shapes.values()), "the shipped step has a free batch axis"
    singles = [{name: rng.random(shape, dtype=np.float32) for name, shape in shapes.items()} for _ in range(2)]
    outputs = [runner.run(feeds) for feeds in singles]
    assert len(backend._compiled) == 1  # batch 2 not compiled yet
    stacked = runner.run({name: np.concatenate([f[name] for f in singles]) for name in shapes})
    assert len(backend._compiled) == 2
    assert {rows for key in backend._compiled for rows in {shape[0] for shape in key}} == {1, 2}
    for row, single in enumerate(outputs):
        for name, value in single.items():
            np.testing.assert_allclose(stacked[name][row : row + 1], value, rtol=1e-4, atol=1e-4)


def test_inputs_whose_free_axes_differ_are_compiled_for_the_shapes_fed(tmp_path):
    """A segment of a cut graph (bf16 islands) reads tensors whose free axis is not the batch: here one input of B
    rows and one of 3B; each is compiled at the shape it is fed, not at the first input's row count."""
    import onnx
    from onnx import TensorProto, helper

    from rafd.runtime.openvino_backend import OpenVinoBackend

    inputs = [helper.make_tensor_value_info(n, TensorProto.FLOAT, ["rows_" + n, 2]) for n in ("frame", "past")]
    outputs = [helper.make_tensor_value_info(n, TensorProto.FLOAT, None) for n in ("frame_out", "past_out")]
    graph = helper.make_graph(
        [helper.make_node("Relu", ["frame"], ["frame_out"]), helper.make_node("Neg", ["past"], ["past_out"])],
        "two_free_axes",
        inputs,
        outputs,
    )
    path = tmp_path / "segment.onnx"
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), path)
    backend = OpenVinoBackend(path, "fp32", threads=1)
    for rows in (1, 2):
        frame = np.arange(2 * rows, dtype=np.float32).reshape(rows, 2) - 1
        past = np.ones((3 * rows, 2), dtype=np.float32)
        out = backend.run({"frame": frame, "past": past})
        np.testing.assert_array_equal(out["frame_out"], np.maximum(frame, 0))
        np.testing.assert_array_equal(out["past_out"], -past)


def test_warm_compiles_every_backend_at_every_batch_before_traffic(shipped_onnx):
    """The service warms the lone run's backend and the crowd's (concurrent streams) at one view and at a whole
    scan's tiles: no request pays OpenVINO's compilation of a static shape."""
    runner = OpenVinoRunner(shipped_onnx, "fp32", threads=2, concurrent_runs=2)
    assert runner.crowd is not None
    runner.warm((1, 21, 21))
    for backend in (runner.backend, runner.crowd):
        assert sorted({key[0][0] for key in backend._compiled}) == [1, 21]
