"""onnxruntime (CPU) vs PyTorch for the exported step graph, T = 1, 2, 4, random weights."""

from __future__ import annotations

import json

import numpy as np
import pytest

from export.verify import Report, radiate_sequence, random_sequence, torch_window, verify_stream
from rafd.model_files import file_sha256
from rafd.runtime import METADATA_KEYS, OnnxRunner
from tests.utils.export_testing import export_step

torch = pytest.importorskip("torch")


@pytest.fixture(scope="module", params=[2, 4], ids=lambda t: f"T{t}")
def exported(request, tmp_path_factory):
    return export_step(tmp_path_factory.mktemp(f"export_T{request.param}"), request.param)


@pytest.fixture(scope="module")
def runner(exported):
    return OnnxRunner(exported.path, threads=2)


def _large_motion(n: int) -> np.ndarray:
    """40 degrees and 6 m per frame: most cells of the previous frame fall outside (the crop is 11 m wide)."""
    steps = np.tile([[6.0, -3.0, np.deg2rad(40.0)]], (n, 1)) * np.where(np.arange(n) % 3 == 2, -1.0, 1.0)[:, None]
    return np.cumsum(steps, axis=0)


def _assert_close(report: Report, cases: int) -> None:
    assert report.ok, "\n".join(report.lines())
    assert report.cases["random"] == cases
    diffs = report.diffs["random"]
    assert diffs["heatmap"].max_abs < 1e-4 and diffs["flow"].max_abs < 1e-4
    assert diffs["boxes"].unmatched == 0 and diffs["boxes"].boundary_swaps == 0  # K = 8 real peaks: no ties


def test_graph_inputs_and_outputs_follow_the_contract(exported, runner):
    cfg = exported.cfg
    S, F, K = cfg.input_size, cfg.feature_size, cfg.head.num_queries
    inputs = {i.name: i.shape for i in runner.backend.session.get_inputs()}
    assert list(inputs)[:2] == ["frame", "pose"]
    assert inputs["frame"] == ["batch", 1, S, S] and inputs["pose"] == ["batch", 3]
    caches = [name for name in inputs if name.startswith("cache.")]
    assert len(caches) == len(inputs) - 2 and caches
    outputs = {o.name: o.shape for o in runner.backend.session.get_outputs()}
    assert outputs["heatmap"] == ["batch", 1, F, F] and outputs["scores"] == ["batch", K]
    assert outputs["boxes"] == ["batch", K, 5] and outputs["flow"] == ["batch", 2, F, F]
    assert outputs["frames_used"] == ["batch"]
    for name in caches:  # every cache input is fed back from an output of its shape
        assert outputs["new_" + name] == inputs[name]
    assert set(outputs) == {"heatmap", "scores", "boxes", "flow", "frames_used"} | {"new_" + n for n in caches}


def test_metadata_is_complete(exported, runner):
    meta = runner.metadata
    assert set(METADATA_KEYS) <= set(meta)
    assert runner.config == exported.cfg
    assert meta["checkpoint_sha256"] == file_sha256(exported.checkpoint)
    assert int(meta["input_size"]) == exported.cfg.input_size
    assert int(meta["num_frames"]) == exported.cfg.num_frames
    assert float(meta["resolution"]) == exported.cfg.resolution
    assert json.loads(meta["class_names"]) == list(exported.cfg.class_names)
    assert meta["opset"] == "17" and meta["exporter"] == exported.result.exporter and meta["batch"] == "dynamic"


def test_stream_equals_padded_window_at_every_frame(exported, runner):
    frames, poses = random_sequence(exported.cfg, 10, seed=2)
    report = Report()
    verify_stream(runner, exported.model, [(frames, poses)], report, "random")  # warm-up frames included
    _assert_close(report, 10)


def test_the_first_frame_is_one_graph_run(exported, runner, monkeypatch):
    """The model warms itself up: a stream's first frame costs one run, like every other."""
    runs = []
    original = runner.run
    monkeypatch.setattr(runner, "run", lambda feeds: runs.append(1) or original(feeds))
    frames, poses = random_sequence(exported.cfg, 2, seed=8)
    state = runner.new_state()
    for n in range(2):
        _, state = runner.step(state, frames[n : n + 1], poses[n : n + 1])
    assert len(runs) == 2


def test_views_step_as_one_batch_each_with_its_own_window(exported, runner):
    views = [random_sequence(exported.cfg, exported.cfg.num_frames + 2, seed=seed) for seed in (10, 11, 12)]
    report = Report()
    verify_stream(runner, exported.model, views, report, "random")
    _assert_close(report, 3 * (exported.cfg.num_frames + 2))


def test_a_batch_may_mix_new_and_started_streams(exported, runner):
    """The warm-up is decided per row of the batch (cache frames 0): a new stream's row beside a started one's
    answers as each does alone."""
    cfg = exported.cfg
    frames, poses = random_sequence(cfg, 3, seed=13)
    started = runner.new_state()
    for n in range(2):
        _, started = runner.step(started, frames[n : n + 1], poses[n : n + 1])
    fresh = {name: np.zeros_like(value) for name, value in started.cache.items()}
    motion = np.array([[0.4, 1.1, 0.03]], np.float32)
    feeds = {
        "frame": np.concatenate([frames[2:3], frames[2:3]])[:, None],
        "pose": np.concatenate([motion, np.zeros_like(motion)]),
        **{name: np.concatenate([started.cache[name], fresh[name]]) for name in started.cache},
    }
    together = runner.run(feeds)
    alone_started = runner.run({name: value[:1] for name, value in feeds.items()})
    alone_fresh = runner.run({name: value[1:] for name, value in feeds.items()})
    for name in ("heatmap", "scores", "flow", "frames_used"):
        np.testing.assert_allclose(together[name][:1], alone_started[name], atol=1e-5)
        np.testing.assert_allclose(together[name][1:], alone_fresh[name], atol=1e-5)
    assert list(together["frames_used"]) == [min(3, cfg.num_frames), 1]


def test_large_rotation_and_translation_still_agree(exported, runner):
    frames, _ = random_sequence(exported.cfg, 7, seed=4)
    poses = _large_motion(7)
    report = Report()
    verify_stream(runner, exported.model, [(frames, poses)], report, "random")
    _assert_close(report, 7)
    # the motion really moves content off the grid: the flows of such a window are not those of a static one
    T = exported.cfg.num_frames
    window = torch_window(exported.model, frames[:T], poses[:T])
    static = torch_window(exported.model, frames[:T], np.zeros((T, 3)))
    assert np.abs(window["flow"] - static["flow"]).max() > 1e-3


def test_large_world_coordinates_lose_no_precision(exported, runner):
    """UTM-sized world poses: the runner takes differences in float64 before the graph's float32."""
    frames, poses = random_sequence(exported.cfg, 6, seed=14)
    far = poses + np.array([5.2e5, 5.7e6, 0.0])
    near_result, far_result = [], []
    for world, out in ((poses, near_result), (far, far_result)):
        state = runner.new_state()
        for n in range(6):
            result, state = runner.step(state, frames[n : n + 1], world[n : n + 1])
            out.append(result)
    for a, b in zip(near_result, far_result):
        np.testing.assert_allclose(a.heatmap, b.heatmap, atol=1e-4)
        np.testing.assert_allclose(a.flow, b.flow, atol=1e-4)


def test_step_is_pure_with_the_real_model(exported, runner):
    frames, poses = random_sequence(exported.cfg, 5, seed=5)
    state = runner.new_state()
    for n in range(3):
        _, state = runner.step(state, frames[n : n + 1], poses[n : n + 1])
    first, _ = runner.step(state, frames[3:4], poses[3:4])
    runner.step(state, frames[4:5], poses[4:5])
    again, _ = runner.step(state, frames[3:4], poses[3:4])
    for name in ("heatmap", "boxes", "scores", "flow"):
        np.testing.assert_array_equal(getattr(first, name), getattr(again, name))
    assert all(not value.flags.writeable for value in state.cache.values())
    assert state.nbytes == sum(value.nbytes for value in state.cache.values()) + 3 * 8


def test_a_state_of_other_views_is_refused(exported, runner):
    frames, poses = random_sequence(exported.cfg, 2, seed=15)
    _, state = runner.step(runner.new_state(), frames[:1], poses[:1])
    with pytest.raises(ValueError, match="holds 1 views"):
        runner.step(state, np.concatenate([frames[1:], frames[1:]]), np.concatenate([poses[1:], poses[1:]]))


def test_single_frame_model(tmp_path):
    exported = export_step(tmp_path, 1)
    frames, poses = random_sequence(exported.cfg, 3, seed=6)
    runner = OnnxRunner(exported.path)
    assert runner.cache_names == ()
    report = Report()
    verify_stream(runner, exported.model, [(frames, poses)], report, "random")
    assert report.ok, "\n".join(report.lines())
    assert "flow" not in report.diffs["random"]
    result, state = runner.step(runner.new_state(), frames[:1], poses[:1])
    assert result.flow is None and result.frames_used == state.frames_used == 1


def test_real_radiate_frames(radiate_sample, exported, runner):
    frames, poses = radiate_sequence(radiate_sample, exported.cfg, 6)
    assert frames.shape == (6, exported.cfg.input_size, exported.cfg.input_size) and 0.0 <= frames.min()
    report = Report()
    verify_stream(runner, exported.model, [(frames, poses)], report, "radiate")
    assert report.ok, "\n".join(report.lines())


def test_shipped_onnx_matches_the_shipped_checkpoint(radiate_sample_or_none):
    from rafd.assets import default_checkpoint, default_onnx
    from rafd.model.checkpoint import load_checkpoint

    checkpoint, onnx_path = default_checkpoint(), default_onnx()
    model, cfg, _ = load_checkpoint(checkpoint)
    runner = OnnxRunner(onnx_path)
    assert runner.config == cfg
    assert runner.metadata["checkpoint_sha256"] == file_sha256(checkpoint)
    report = Report()
    verify_stream(runner, model, [random_sequence(cfg, cfg.num_frames + 2, seed=7)], report, "random")
    if radiate_sample_or_none is not None:
        real = radiate_sequence(radiate_sample_or_none, cfg, cfg.num_frames + 2)
        verify_stream(runner, model, [real], report, "radiate")
    assert report.ok, "\n".join(report.lines())
