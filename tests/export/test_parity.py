"""onnxruntime (CPU) vs PyTorch for the exported step and window graphs, T = 1, 2, 4, random weights."""

from __future__ import annotations

import json

import numpy as np
import pytest

from export.verify import Report, radiate_sequence, random_sequence, torch_window, verify_stream, verify_windows
from rafd.model_files import file_sha256
from rafd.runtime import METADATA_KEYS, OnnxRunner
from tests.utils.export_testing import export_forms

torch = pytest.importorskip("torch")


@pytest.fixture(scope="module", params=[2, 4], ids=lambda t: f"T{t}")
def exported(request, tmp_path_factory):
    return export_forms(tmp_path_factory.mktemp(f"export_T{request.param}"), request.param)


@pytest.fixture(scope="module")
def runners(exported):
    return {form: OnnxRunner(path, threads=2) for form, path in exported.paths.items()}


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


def test_graph_inputs_and_outputs_follow_the_contract(exported, runners):
    cfg, T = exported.cfg, exported.cfg.num_frames
    S, F, K = cfg.input_size, cfg.feature_size, cfg.head.num_queries
    C = int(runners["step"].metadata["feature_channels"])
    step = {i.name: i.shape for i in runners["step"].session.get_inputs()}
    expected = {
        "frame": [1, 1, S, S],
        "poses": [1, T, 3],
        "past_features": [1, T - 1, C, F, F],
        "past_flow_features": [1, C // 2, F, F],
    }
    if T == 4:
        expected["past_flows"] = [1, T - 2, 2, F, F]
    assert step == expected
    outputs = {o.name: o.shape for o in runners["step"].session.get_outputs()}
    assert outputs == {
        "heatmap": [1, 1, F, F],
        "scores": [1, K],
        "boxes": [1, K, 5],
        "flow": [1, T - 1, 2, F, F],
        "features": [1, C, F, F],
        "flow_features": [1, C // 2, F, F],
    }
    window = {i.name: i.shape for i in runners["window"].session.get_inputs()}
    assert window == {"frames": [1, T, 1, S, S], "poses": [1, T, 3]}


def test_metadata_is_complete(exported, runners):
    for form, runner in runners.items():
        meta = runner.metadata
        assert set(METADATA_KEYS) <= set(meta)
        assert runner.config == exported.cfg and runner.form == form == meta["form"]
        assert meta["checkpoint_sha256"] == file_sha256(exported.checkpoint)
        assert int(meta["input_size"]) == exported.cfg.input_size
        assert int(meta["num_frames"]) == exported.cfg.num_frames
        assert float(meta["resolution"]) == exported.cfg.resolution
        assert json.loads(meta["class_names"]) == list(exported.cfg.class_names)
        assert meta["opset"] == "17" and meta["exporter"] == exported.results[form].exporter


def test_window_form_matches_torch(exported, runners):
    frames, poses = random_sequence(exported.cfg, exported.cfg.num_frames + 2, seed=1)
    report = Report()
    verify_windows(runners["window"], exported.model, frames, poses, report, "random")
    _assert_close(report, 3)


def test_stream_equals_padded_window_at_every_frame(exported, runners):
    frames, poses = random_sequence(exported.cfg, 10, seed=2)
    report = Report()
    verify_stream(runners["step"], exported.model, frames, poses, report, "random")  # warm-up frames included
    _assert_close(report, 10)


def test_window_form_streams_like_the_step_form(exported, runners):
    frames, poses = random_sequence(exported.cfg, 6, seed=3)
    states = {form: runner.new_state() for form, runner in runners.items()}
    for frame, pose in zip(frames, poses):
        results = {}
        for form, runner in runners.items():
            results[form], states[form] = runner.step(states[form], frame, pose)
        assert results["step"].frames_used == results["window"].frames_used
        np.testing.assert_allclose(results["step"].heatmap, results["window"].heatmap, rtol=1e-3, atol=1e-4)
        np.testing.assert_allclose(results["step"].flow, results["window"].flow, rtol=1e-3, atol=1e-4)


def test_large_rotation_and_translation_still_agree(exported, runners):
    frames, _ = random_sequence(exported.cfg, 7, seed=4)
    poses = _large_motion(7)
    report = Report()
    verify_stream(runners["step"], exported.model, frames, poses, report, "random")
    verify_windows(runners["window"], exported.model, frames, poses, report, "random")
    _assert_close(report, 7 + 7 - exported.cfg.num_frames + 1)
    # the motion really moves content off the grid: the flows of such a window are not those of a static one
    window = torch_window(exported.model, frames[: exported.cfg.num_frames], poses[: exported.cfg.num_frames])
    static = torch_window(exported.model, frames[: exported.cfg.num_frames], np.zeros((exported.cfg.num_frames, 3)))
    assert np.abs(window["flow"] - static["flow"]).max() > 1e-3


def test_step_is_pure_with_the_real_model(exported, runners):
    runner = runners["step"]
    frames, poses = random_sequence(exported.cfg, 5, seed=5)
    state = runner.new_state()
    for n in range(3):
        _, state = runner.step(state, frames[n], poses[n])
    first, _ = runner.step(state, frames[3], poses[3])
    runner.step(state, frames[4], poses[4])
    again, _ = runner.step(state, frames[3], poses[3])
    for name in ("heatmap", "boxes", "scores", "flow"):
        np.testing.assert_array_equal(getattr(first, name), getattr(again, name))
    C, F, M = int(runner.metadata["feature_channels"]), exported.cfg.feature_size, exported.cfg.flow_size
    T = exported.cfg.num_frames
    # T-1 features, T-2 pair flows, T-1 poses and the newest frame's flow features (phi output, C/2 channels)
    assert state.nbytes == (T - 1) * C * F * F * 4 + (T - 2) * 2 * F * F * 4 + (T - 1) * 3 * 8 + C // 2 * M * M * 4


def test_single_frame_model(tmp_path):
    exported = export_forms(tmp_path, 1)
    frames, poses = random_sequence(exported.cfg, 3, seed=6)
    runner = OnnxRunner(exported.paths["step"])
    assert runner.input_names == ("frame", "poses")
    report = Report()
    verify_stream(runner, exported.model, frames, poses, report, "random")
    verify_windows(OnnxRunner(exported.paths["window"]), exported.model, frames, poses, report, "random")
    assert report.ok, "\n".join(report.lines())
    assert "flow" not in report.diffs["random"]
    result, state = runner.step(runner.new_state(), frames[0], poses[0])
    assert result.flow is None and result.frames_used == state.frames_used == 1


def test_real_radiate_frames(radiate_sample, exported, runners):
    frames, poses = radiate_sequence(radiate_sample, exported.cfg, 6)
    assert frames.shape == (6, exported.cfg.input_size, exported.cfg.input_size) and 0.0 <= frames.min()
    report = Report()
    verify_stream(runners["step"], exported.model, frames, poses, report, "radiate")
    assert report.ok, "\n".join(report.lines())


def test_shipped_onnx_matches_the_shipped_checkpoint(radiate_sample_or_none):
    assets = pytest.importorskip("rafd.assets", reason="rafd.assets is not there yet")
    try:
        checkpoint, onnx_path = assets.default_checkpoint(), assets.default_onnx()
    except FileNotFoundError as error:
        pytest.skip(f"the shipped model is not built yet: {error}")
    from rafd.model.checkpoint import load_checkpoint

    model, cfg, _ = load_checkpoint(checkpoint)
    runner = OnnxRunner(onnx_path)
    assert runner.form == "step" and runner.config == cfg
    assert runner.metadata["checkpoint_sha256"] == file_sha256(checkpoint)
    report = Report()
    verify_stream(runner, model, *random_sequence(cfg, cfg.num_frames + 2, seed=7), report, "random")
    if radiate_sample_or_none is not None:
        verify_stream(
            runner, model, *radiate_sequence(radiate_sample_or_none, cfg, cfg.num_frames + 2), report, "radiate"
        )
    assert report.ok, "\n".join(report.lines())
