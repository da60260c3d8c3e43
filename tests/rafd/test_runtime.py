"""rafd.runtime without torch: warm-up padding, pose handling, the first-frame procedure, state purity.

The runner is exercised on a hand-built ONNX step graph with the contract's inputs and outputs whose outputs are
simple functions of the window (features = average-pooled frame, pair flow = [new - previous features,
previous features + x displacement], heatmap = weighted sums of features, flows and poses), so every step can be
recomputed in numpy from the warm-up-padded window. Parity with the real model is tested in tests/export/.
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
from rafd.runtime import OnnxRunner, StreamState, poses_in_newest_frame, window_from_history

onnx = pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")
from onnx import TensorProto, helper, numpy_helper  # noqa: E402

S, STRIDE, K = 16, 4, 5
F = S // STRIDE


def _config(T: int) -> RaFDConfig:
    return RaFDConfig.tiny(input_size=S, num_frames=T, output_stride=STRIDE)


def _weights(T: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    w_feat = np.arange(1, T + 1, dtype=np.float32).reshape(1, T, 1, 1, 1)
    w_flow = (np.arange(2 * max(T - 1, 0), dtype=np.float32) * 0.1 + 0.5).reshape(1, max(T - 1, 0), 2, 1, 1)
    w_pose = np.linspace(0.1, 1.0, 3 * T, dtype=np.float32).reshape(1, T, 3)
    return w_feat, w_flow, w_pose


def build_fake_step_graph(path, T: int, metadata: dict[str, str] | None = None) -> None:
    """An ONNX step graph with the contract's interface (C = 1) and simple, checkable outputs."""
    w_feat, w_flow, w_pose = _weights(T)
    f32 = TensorProto.FLOAT
    inputs = [
        helper.make_tensor_value_info("frame", f32, [1, 1, S, S]),
        helper.make_tensor_value_info("poses", f32, [1, T, 3]),
    ]
    inits = [
        numpy_helper.from_array(w_pose, "w_pose"),
        numpy_helper.from_array(np.array([1, F * F], np.int64), "flat_shape"),
        numpy_helper.from_array(np.array([0], np.int64), "zero"),
        numpy_helper.from_array(np.array([K], np.int64), "k"),
        numpy_helper.from_array(np.array([1], np.int64), "one"),
        numpy_helper.from_array(np.array([-1], np.int64), "minus_one"),
        numpy_helper.from_array(np.array([1, 1, 5], np.int64), "tile"),
    ]
    nodes = [
        helper.make_node(
            "AveragePool", ["frame"], ["features"], kernel_shape=[STRIDE, STRIDE], strides=[STRIDE, STRIDE]
        ),
        helper.make_node("Mul", ["poses", "w_pose"], ["pose_w"]),
        helper.make_node("ReduceSum", ["pose_w"], ["pose_term"], keepdims=0),
    ]
    outputs = ["heatmap", "scores", "boxes"]
    if T == 1:
        nodes.append(helper.make_node("Add", ["features", "pose_term"], ["heatmap"]))
    else:
        inputs.append(helper.make_tensor_value_info("past_features", f32, [1, T - 1, 1, F, F]))
        inits += [
            numpy_helper.from_array(w_feat, "w_feat"),
            numpy_helper.from_array(w_flow, "w_flow"),
            numpy_helper.from_array(np.array(T - 2, np.int64), "prev_index"),
            numpy_helper.from_array(np.array(T - 1, np.int64), "last_index"),
            numpy_helper.from_array(np.array([1, 1, 1, 1], np.int64), "four_d"),
            numpy_helper.from_array(np.array([1, 2], np.int64), "axes12"),
        ]
        nodes += [
            helper.make_node("Gather", ["past_features", "prev_index"], ["prev"], axis=1),
            helper.make_node("Sub", ["features", "prev"], ["dfeat"]),
            helper.make_node("Gather", ["poses", "last_index"], ["p_last"], axis=1),
            helper.make_node("Gather", ["poses", "prev_index"], ["p_prev"], axis=1),
            helper.make_node("Sub", ["p_last", "p_prev"], ["dpose"]),
            helper.make_node("Slice", ["dpose", "zero", "one", "one"], ["dx"]),
            helper.make_node("Reshape", ["dx", "four_d"], ["dx4"]),
            helper.make_node("Add", ["prev", "dx4"], ["ch1"]),
            helper.make_node("Concat", ["dfeat", "ch1"], ["new_flow"], axis=1),
            helper.make_node("Unsqueeze", ["new_flow", "one"], ["new_flow5"]),
            helper.make_node("Unsqueeze", ["features", "one"], ["features5"]),
            helper.make_node("Concat", ["past_features", "features5"], ["window"], axis=1),
            helper.make_node("Mul", ["window", "w_feat"], ["window_w"]),
            helper.make_node("ReduceSum", ["window_w", "one"], ["heat_features"], keepdims=0),
        ]
        if T > 2:
            inputs.append(helper.make_tensor_value_info("past_flows", f32, [1, T - 2, 2, F, F]))
            nodes.append(helper.make_node("Concat", ["past_flows", "new_flow5"], ["flow"], axis=1))
        else:
            nodes.append(helper.make_node("Identity", ["new_flow5"], ["flow"]))
        nodes += [
            helper.make_node("Mul", ["flow", "w_flow"], ["flow_w"]),
            helper.make_node("ReduceSum", ["flow_w", "axes12"], ["heat_flow"], keepdims=0),  # [1,F,F]
            helper.make_node("Add", ["heat_features", "heat_flow"], ["heat_sum"]),
            helper.make_node("Add", ["heat_sum", "pose_term"], ["heatmap"]),
        ]
        outputs += ["flow", "features"]
    nodes += [
        helper.make_node("Reshape", ["heatmap", "flat_shape"], ["flat"]),
        helper.make_node("Slice", ["flat", "zero", "k", "one"], ["first_k"]),
        helper.make_node("Sigmoid", ["first_k"], ["scores"]),
        helper.make_node("Unsqueeze", ["scores", "minus_one"], ["scores3"]),
        helper.make_node("Tile", ["scores3", "tile"], ["boxes"]),
    ]
    shapes = {
        "heatmap": [1, 1, F, F],
        "scores": [1, K],
        "boxes": [1, K, 5],
        "flow": [1, T - 1, 2, F, F],
        "features": [1, 1, F, F],
    }
    graph = helper.make_graph(
        nodes,
        "fake_step",
        inputs,
        [helper.make_tensor_value_info(n, f32, shapes[n]) for n in outputs],
        initializer=inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    cfg = _config(T)
    meta = {
        "config": cfg.to_json(),
        "input_size": str(S),
        "resolution": str(cfg.resolution),
        "num_frames": str(T),
        "class_names": json.dumps(list(cfg.class_names)),
        "checkpoint_sha256": "0" * 64,
        "version": "test",
        "form": "step",
        "feature_channels": "1",
    }
    for key, value in (meta if metadata is None else metadata).items():
        model.metadata_props.add(key=key, value=value)
    onnx.checker.check_model(model)
    onnx.save(model, str(path))


def reference(frames: np.ndarray, poses: np.ndarray, T: int) -> dict[str, np.ndarray | None]:
    """The fake graph's outputs for one padded window, in numpy."""
    w_feat, w_flow, w_pose = _weights(T)
    feats = frames.reshape(T, F, STRIDE, F, STRIDE).mean(axis=(2, 4))  # [T, F, F]
    heat = (feats * w_feat.reshape(T, 1, 1)).sum(0) + (poses_in_newest_frame(poses) * w_pose[0]).sum()
    flow = None
    if T > 1:
        # each pair's flow was computed when its later frame was the newest: x displacement in that frame
        dx = [-poses_in_newest_frame(poses[t - 1 : t + 1])[0, 0] for t in range(1, T)]
        flow = np.stack([np.stack([feats[t] - feats[t - 1], feats[t - 1] + dx[t - 1]]) for t in range(1, T)])
        heat = heat + (flow * w_flow[0]).sum(axis=(0, 1))
    scores = 1.0 / (1.0 + np.exp(-heat.reshape(-1)[:K]))
    return {"heatmap": heat, "scores": scores, "flow": flow}


def _sequence(n: int, seed: int = 0, offset: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    frames = rng.random((n, S, S)).astype(np.float32)
    poses = np.cumsum(rng.normal(0.0, 1.0, (n, 3)) * [2.0, 2.0, 0.3], axis=0) + [offset, offset, 0.0]
    return frames, poses


@pytest.fixture(scope="module", params=[1, 2, 4], ids=lambda t: f"T{t}")
def runner(request, tmp_path_factory) -> OnnxRunner:
    path = tmp_path_factory.mktemp("fake") / f"fake_T{request.param}.onnx"
    build_fake_step_graph(path, request.param)
    return OnnxRunner(path, threads=1)


def test_import_is_torch_free():
    code = (
        "import sys, rafd.runtime; assert 'torch' not in sys.modules, 'torch imported'; "
        "assert 'onnxruntime' not in sys.modules, 'onnxruntime imported at import time'"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


def test_window_from_history_pads_the_old_end_with_the_oldest_frame():
    frames = [np.full((2, 2), i, np.float32) for i in range(6)]
    poses = np.arange(18, dtype=np.float64).reshape(6, 3)
    window, window_poses = window_from_history(frames[:2], poses[:2], 4)
    assert [w[0, 0] for w in window] == [0, 0, 0, 1]
    np.testing.assert_array_equal(window_poses, poses[[0, 0, 0, 1]])
    window, window_poses = window_from_history(frames, poses, 4)  # longer history: the last T frames
    assert [w[0, 0] for w in window] == [2, 3, 4, 5]
    np.testing.assert_array_equal(window_poses, poses[2:])
    with pytest.raises(ValueError):
        window_from_history(frames[:2], poses[:3], 4)
    with pytest.raises(ValueError):
        window_from_history([], np.zeros((0, 3)), 4)


def test_poses_in_newest_frame_keep_relative_poses_of_large_world_poses():
    rng = np.random.default_rng(1)
    poses = np.cumsum(rng.normal(0.0, 3.0, (4, 3)), axis=0) + [523_456.0, 6_212_345.0, 0.0]  # UTM-sized
    local = poses_in_newest_frame(poses)
    assert local.dtype == np.float32
    np.testing.assert_allclose(local[-1], 0.0, atol=1e-12)
    for a in range(4):
        for b in range(4):
            expected = relative_pose(poses[a], poses[b])
            got = relative_pose(local[a].astype(np.float64), local[b].astype(np.float64))
            np.testing.assert_allclose(got[:2], expected[:2], atol=2e-5)
            assert abs((got[2] - expected[2] + np.pi) % (2 * np.pi) - np.pi) < 1e-6


def test_runner_reads_config_and_metadata(runner):
    assert runner.config.input_size == S and runner.form == "step"
    assert runner.metadata["checkpoint_sha256"] == "0" * 64
    assert runner.threads == 1


def test_stream_equals_padded_windows_at_every_frame(runner):
    T = runner.config.num_frames
    frames, poses = _sequence(7)
    state = runner.new_state()
    assert state.frames_used == 0 and state.nbytes == 0
    for n in range(len(frames)):
        result, state = runner.step(state, frames[n], poses[n])
        expected = reference(*window_from_history(frames[: n + 1], poses[: n + 1], T), T)
        assert result.frames_used == state.frames_used == min(n + 1, T)
        np.testing.assert_allclose(result.heatmap, expected["heatmap"], rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(result.scores, expected["scores"], rtol=1e-5, atol=1e-6)
        assert result.boxes.shape == (K, 5)
        if T == 1:
            assert result.flow is None
        else:
            assert result.flow.shape == (T - 1, 2, F, F)
            np.testing.assert_allclose(result.flow, expected["flow"], rtol=1e-5, atol=1e-5)


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
    snapshot = [a.copy() for a in state.features + state.flows + state.poses]
    first, new_a = runner.step(state, frames[3], poses[3])
    other, _ = runner.step(state, frames[4], poses[4])  # a different frame from the same old state
    again, new_b = runner.step(state, frames[3], poses[3])
    np.testing.assert_array_equal(first.heatmap, again.heatmap)
    np.testing.assert_array_equal(first.scores, again.scores)
    assert not np.array_equal(first.heatmap, other.heatmap)
    for before, after in zip(snapshot, state.features + state.flows + state.poses):
        np.testing.assert_array_equal(before, after)
        assert not after.flags.writeable
    assert new_a.frames_used == new_b.frames_used == min(4, runner.config.num_frames)
    with pytest.raises(dataclasses.FrozenInstanceError):
        state.frames_used = 0  # type: ignore[misc]


def test_state_holds_padded_caches_and_counts_shared_arrays_once(runner):
    T = runner.config.num_frames
    frames, poses = _sequence(1)
    _, state = runner.step(runner.new_state(), frames[0], poses[0])
    assert isinstance(state, StreamState)
    assert len(state.features) == max(T - 1, 0) and len(state.flows) == max(T - 2, 0)
    # one feature map, one self-pair flow and one pose after the first frame (padding repeats them)
    expected = (F * F * 4 + 24 if T > 1 else 0) + (2 * F * F * 4 if T > 2 else 0)
    assert state.nbytes == expected


@pytest.mark.parametrize(
    "bad",
    [
        np.zeros((S, S), np.float64),
        np.zeros((S + 1, S), np.float32),
        np.full((S, S), 1.5, np.float32),
        np.full((S, S), np.nan, np.float32),
    ],
)
def test_bad_frames_are_refused(runner, bad):
    with pytest.raises(ValueError):
        runner.step(runner.new_state(), bad, np.zeros(3))


@pytest.mark.parametrize("pose", [np.zeros(2), np.array([0.0, np.inf, 0.0])])
def test_bad_poses_are_refused(runner, pose):
    with pytest.raises(ValueError):
        runner.step(runner.new_state(), np.zeros((S, S), np.float32), pose)


def test_foreign_onnx_and_missing_files_are_refused(tmp_path):
    path = tmp_path / "foreign.onnx"
    build_fake_step_graph(path, 2, metadata={"producer": "someone else"})
    with pytest.raises(ValueError, match="not a RaFD export"):
        OnnxRunner(path)
    with pytest.raises(FileNotFoundError):
        OnnxRunner(tmp_path / "missing.onnx")
    garbage = tmp_path / "garbage.onnx"
    garbage.write_bytes(b"not a protobuf")
    with pytest.raises(ValueError, match="garbage.onnx"):
        OnnxRunner(garbage)
