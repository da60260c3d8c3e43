"""rafd.runtime without torch: the runner carries the graph's cache, feeds each view's pose in its previous pose's
frame, keeps states pure, and refuses what does not follow the contract.

The runner is exercised on a hand-built ONNX step graph with the contract's interface whose cache is a running sum
of pooled frames and a frame count, so every step can be recomputed in numpy. That the real model's cache and
warm-up equal its padded windows is tested against PyTorch in tests/export/.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest

from rafd.config import RaFDConfig
from rafd.geometry import relative_pose
from rafd.runtime import OnnxRunner, StreamState

onnx = pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")
from onnx import TensorProto, helper, numpy_helper  # noqa: E402

S, STRIDE, K = 16, 4, 5
F = S // STRIDE
W_POSE = np.array([0.5, -0.25, 2.0], np.float32)


def _metadata(T: int = 4) -> dict[str, str]:
    cfg = RaFDConfig.tiny(input_size=S, num_frames=T, output_stride=STRIDE)
    return {
        "config": cfg.to_json(),
        "input_size": str(S),
        "resolution": str(cfg.resolution),
        "num_frames": str(T),
        "class_names": json.dumps(list(cfg.class_names)),
        "checkpoint_sha256": "0" * 64,
        "version": "test",
    }


def build_fake_step_graph(path, metadata: dict[str, str] | None = None, drop_output: str | None = None) -> None:
    """A step graph (free batch axis) whose cache is a running sum of pooled frames and a frame count; heatmap =
    the sum + pose . W_POSE, flow = the pooled frame twice."""
    f32 = TensorProto.FLOAT
    inputs = [
        helper.make_tensor_value_info("frame", f32, ["batch", 1, S, S]),
        helper.make_tensor_value_info("pose", f32, ["batch", 3]),
        helper.make_tensor_value_info("cache.sum", f32, ["batch", 1, F, F]),
        helper.make_tensor_value_info("cache.frames", f32, ["batch"]),
    ]
    inits = [
        numpy_helper.from_array(W_POSE, "w_pose"),
        numpy_helper.from_array(np.array([1.0], np.float32), "one_f"),
        numpy_helper.from_array(np.array([-1, F * F], np.int64), "flat_shape"),
        numpy_helper.from_array(np.array([-1, 1, 1, 1], np.int64), "per_row"),
        numpy_helper.from_array(np.array([0], np.int64), "zero"),
        numpy_helper.from_array(np.array([K], np.int64), "k"),
        numpy_helper.from_array(np.array([1], np.int64), "one"),
        numpy_helper.from_array(np.array([-1], np.int64), "minus_one"),
        numpy_helper.from_array(np.array([1, 1, 5], np.int64), "tile"),
    ]
    nodes = [
        helper.make_node("AveragePool", ["frame"], ["features"], kernel_shape=[STRIDE, STRIDE], strides=[STRIDE] * 2),
        helper.make_node("Add", ["cache.sum", "features"], ["new_cache.sum"]),
        helper.make_node("Add", ["cache.frames", "one_f"], ["new_cache.frames"]),
        helper.make_node("Identity", ["new_cache.frames"], ["frames_used"]),
        helper.make_node("Mul", ["pose", "w_pose"], ["pose_w"]),
        helper.make_node("ReduceSum", ["pose_w", "one"], ["pose_term"], keepdims=0),
        helper.make_node("Reshape", ["pose_term", "per_row"], ["pose_term4"]),
        helper.make_node("Add", ["new_cache.sum", "pose_term4"], ["heatmap"]),
        helper.make_node("Concat", ["features", "features"], ["flow"], axis=1),
        helper.make_node("Reshape", ["heatmap", "flat_shape"], ["flat"]),
        helper.make_node("Slice", ["flat", "zero", "k", "one"], ["first_k"]),
        helper.make_node("Sigmoid", ["first_k"], ["scores"]),
        helper.make_node("Unsqueeze", ["scores", "minus_one"], ["scores3"]),
        helper.make_node("Tile", ["scores3", "tile"], ["boxes"]),
    ]
    shapes = {
        "heatmap": ["batch", 1, F, F],
        "scores": ["batch", K],
        "boxes": ["batch", K, 5],
        "flow": ["batch", 2, F, F],
        "frames_used": ["batch"],
        "new_cache.sum": ["batch", 1, F, F],
        "new_cache.frames": ["batch"],
    }
    outputs = [helper.make_tensor_value_info(n, f32, s) for n, s in shapes.items() if n != drop_output]
    graph = helper.make_graph(nodes, "fake_step", inputs, outputs, initializer=inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    for key, value in (_metadata() if metadata is None else metadata).items():
        model.metadata_props.add(key=key, value=value)
    onnx.checker.check_model(model)
    onnx.save(model, str(path))


def _sequence(n: int, views: int = 1, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """frames [n, V, S, S], world poses [n, V, 3]."""
    rng = np.random.default_rng(seed)
    frames = rng.random((n, views, S, S)).astype(np.float32)
    poses = np.cumsum(rng.normal(0.0, 1.0, (n, views, 3)) * [2.0, 2.0, 0.3], axis=0)
    return frames, poses


def _pooled(frames: np.ndarray) -> np.ndarray:
    return frames.reshape(*frames.shape[:-2], F, STRIDE, F, STRIDE).mean(axis=(-3, -1))


@pytest.fixture(scope="module")
def runner(tmp_path_factory) -> OnnxRunner:
    path = tmp_path_factory.mktemp("fake") / "fake.onnx"
    build_fake_step_graph(path)
    return OnnxRunner(path, threads=1)


def test_import_is_torch_free():
    code = (
        "import sys, rafd.runtime; assert 'torch' not in sys.modules, 'torch imported'; "
        "assert 'onnxruntime' not in sys.modules, 'onnxruntime imported at import time'"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_runner_reads_config_metadata_and_cache(runner):
    assert runner.config.input_size == S and runner.cache_names == ("cache.sum", "cache.frames")
    assert runner.metadata["checkpoint_sha256"] == "0" * 64
    assert runner.threads == 1


@pytest.mark.parametrize("views", [1, 3])
def test_the_cache_is_carried_and_poses_are_relative(runner, views):
    frames, poses = _sequence(5, views)
    state = runner.new_state()
    assert state.frames_used == 0 and state.nbytes == 0 and state.views == 0
    total = np.zeros((views, F, F))
    for n in range(len(frames)):
        result, state = runner.step(state, frames[n], poses[n])
        total = total + _pooled(frames[n])
        motion = np.zeros((views, 3)) if n == 0 else relative_pose(poses[n], poses[n - 1])
        expected = total + (motion * W_POSE).sum(-1)[:, None, None]
        assert result.frames_used == state.frames_used == n + 1 and state.views == views
        np.testing.assert_allclose(result.heatmap, expected, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(result.flow, np.stack([_pooled(frames[n])] * 2, 1), atol=1e-6)
        assert result.boxes.shape == (views, K, 5) and result.view(views - 1).boxes.shape == (K, 5)


def test_large_world_poses_give_the_same_results(runner):
    frames, poses = _sequence(5, seed=2)
    far = poses + [523_456.0, 6_212_345.0, 0.0]
    state_near, state_far = runner.new_state(), runner.new_state()
    for frame, near_pose, far_pose in zip(frames, poses, far):
        near, state_near = runner.step(state_near, frame, near_pose)
        result, state_far = runner.step(state_far, frame, far_pose)
        np.testing.assert_allclose(result.heatmap, near.heatmap, atol=1e-4)


def test_step_is_pure(runner):
    frames, poses = _sequence(6, seed=3)
    state = runner.new_state()
    for n in range(3):
        _, state = runner.step(state, frames[n], poses[n])
    snapshot = {name: value.copy() for name, value in state.cache.items()}
    first, new_a = runner.step(state, frames[3], poses[3])
    other, _ = runner.step(state, frames[4], poses[4])  # a different frame from the same old state
    again, new_b = runner.step(state, frames[3], poses[3])
    np.testing.assert_array_equal(first.heatmap, again.heatmap)
    assert not np.array_equal(first.heatmap, other.heatmap)
    for name, before in snapshot.items():
        np.testing.assert_array_equal(before, state.cache[name])
        assert not state.cache[name].flags.writeable
    assert new_a.frames_used == new_b.frames_used == 4
    assert isinstance(state, StreamState) and state.nbytes == (F * F + 1) * 4 + 3 * 8
    with pytest.raises(dataclasses.FrozenInstanceError):
        state.frames_used = 0  # type: ignore[misc]
    with pytest.raises(TypeError):
        state.cache["cache.sum"] = snapshot["cache.sum"]  # type: ignore[index]


def test_a_state_of_other_views_is_refused(runner):
    frames, poses = _sequence(2, views=2)
    _, state = runner.step(runner.new_state(), frames[0], poses[0])
    with pytest.raises(ValueError, match="holds 2 views"):
        runner.step(state, frames[1][:1], poses[1][:1])


@pytest.mark.parametrize(
    "bad",
    [
        np.zeros((1, S, S), np.float64),
        np.zeros((1, S + 1, S), np.float32),
        np.zeros((S, S), np.float32),
        np.zeros((0, S, S), np.float32),
        np.full((1, S, S), 1.5, np.float32),
        np.full((1, S, S), np.nan, np.float32),
    ],
)
def test_bad_frames_are_refused(runner, bad):
    with pytest.raises(ValueError):
        runner.step(runner.new_state(), bad, np.zeros((1, 3)))


@pytest.mark.parametrize("pose", [np.zeros(3), np.zeros((1, 2)), np.array([[0.0, np.inf, 0.0]])])
def test_bad_poses_are_refused(runner, pose):
    with pytest.raises(ValueError):
        runner.step(runner.new_state(), np.zeros((1, S, S), np.float32), pose)


def test_foreign_onnx_and_missing_files_are_refused(tmp_path):
    path = tmp_path / "foreign.onnx"
    build_fake_step_graph(path, metadata={"producer": "someone else"})
    with pytest.raises(ValueError, match="not a RaFD export"):
        OnnxRunner(path)
    with pytest.raises(FileNotFoundError):
        OnnxRunner(tmp_path / "missing.onnx")
    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(b"not a protobuf")
    with pytest.raises(ValueError, match="garbage.onnx"):
        OnnxRunner(garbage)


def test_a_cache_input_without_its_output_is_refused(tmp_path):
    path = tmp_path / "uncarried.onnx"
    build_fake_step_graph(path, drop_output="new_cache.sum")
    with pytest.raises(ValueError, match=r"not a RaFD step graph: outputs \['new_cache.sum'\] are missing"):
        OnnxRunner(path)
