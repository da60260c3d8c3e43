"""The answer's flow validity (rafd.flow_validity): per cell of the flow grid, in both flow forms, with its threshold;
0 on the crop's outer ring, 1 inside it for a still vehicle, 0 ahead after a large forward motion, and none at all
(no flow) on a stream's first frame."""

from __future__ import annotations

import base64
import dataclasses
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from rafd.flow_validity import FLOW_VALID_MIN, flow_validity, search_reach_m
from rafd.geometry import relative_pose
from service.app import create_app
from service.pipeline.detector import VALIDITY_STEPS
from service.settings import Settings
from tests.utils.service_testing import FakeOdometry, blob_frame, detect_json, wait_ready

FRAME = blob_frame(128, [(40, 60, 250), (90, 20, 180)])
STILL = (0.0, 0.0, 0.0)


def second_answer(client, stream: str, second_pose, fmt: str = "list", dt: float = 0.5) -> dict:
    """The answer to a stream's second frame (the first at STILL), in flow format `fmt`."""
    first = client.post("/detect", json=detect_json(stream, 1.0, FRAME, STILL))
    assert first.status_code == 200, first.text
    response = client.post(f"/detect?flow_format={fmt}", json=detect_json(stream, 1.0 + dt, FRAME, second_pose))
    assert response.status_code == 200, response.text
    return response.json()


def validity_of(flow: dict) -> np.ndarray:
    shape = (flow["grid"]["height"], flow["grid"]["width"])
    if flow["encoding"] == "base64-float16":
        return np.frombuffer(base64.b64decode(flow["validity"]), "<f2").reshape(shape).astype(np.float64)
    return np.asarray(flow["validity"], dtype=np.float64)


def expected_validity(runner, previous_pose, pose) -> np.ndarray:
    """rafd.flow_validity on the fake model's geometry (128 px, 32 x 32 cells, flow stride 4, global matching)."""
    cfg = runner.config
    reach = search_reach_m(cfg.flow.stride, cfg.resolution, cfg.flow.local_radius)
    relative = relative_pose(np.asarray(previous_pose, np.float64), np.asarray(pose, np.float64))
    return flow_validity(relative, cfg.feature_size, cfg.input_size, cfg.resolution, cfg.flow.stride, reach)


def outer_ring(size: int) -> np.ndarray:
    ring = np.ones((size, size), bool)
    ring[1:-1, 1:-1] = False
    return ring


def test_the_png_form_carries_the_list_forms_values(client):
    """flow_format=png (rafd.flow_png): the same flow to the millimetre and the same validity, in far fewer bytes."""
    from rafd.viz.answer import decode_flow, decode_validity

    pose = (0.3, 1.5, 0.04)
    listed = second_answer(client, "png-list", pose)["flow"]
    packed = second_answer(client, "png-png", pose, fmt="png")["flow"]
    assert packed["encoding"] == "png" and packed["shape"] == listed["shape"]
    np.testing.assert_allclose(decode_flow(packed), decode_flow(listed), atol=1e-9)  # both to 1 mm
    np.testing.assert_array_equal(decode_validity(packed), validity_of(listed))
    assert len(packed["values"]) < len(str(listed["values"])) / 2


def test_validity_comes_in_both_flow_forms_with_the_flows_grid_and_threshold(client, runner):
    pose = (0.3, 1.5, 0.04)
    listed = second_answer(client, "as-list", pose)["flow"]
    encoded = second_answer(client, "as-base64", pose, fmt="base64")["flow"]
    cfg = runner.config
    for flow in (listed, encoded):
        assert flow["validity_min"] == FLOW_VALID_MIN
        assert flow["search_reach_m"] == pytest.approx(search_reach_m(cfg.flow.stride, cfg.resolution, 0), abs=1e-4)
    assert listed["encoding"] == "list" and encoded["encoding"] == "base64-float16"
    assert np.asarray(listed["validity"]).shape == tuple(listed["shape"][1:]) == (32, 32)  # the flow's [Hf, Wf]
    assert len(base64.b64decode(encoded["validity"])) == 2 * 32 * 32  # float16, row-major [Hf, Wf]
    from_list, from_base64 = validity_of(listed), validity_of(encoded)
    np.testing.assert_allclose(from_base64, from_list, atol=1e-3)  # one set of values, two encodings
    np.testing.assert_array_equal(from_base64 >= FLOW_VALID_MIN, from_list >= FLOW_VALID_MIN)
    # rafd.flow_validity rounded DOWN to 0.01: never above it, at most a step below, valid exactly where it is valid
    exact = expected_validity(runner, STILL, pose)
    steps = from_list * VALIDITY_STEPS
    np.testing.assert_allclose(steps, np.round(steps), atol=1e-4)
    assert np.all(from_list <= exact + 1e-6) and np.all(from_list > exact - 1.0 / VALIDITY_STEPS - 1e-6)
    np.testing.assert_array_equal(from_list >= FLOW_VALID_MIN, exact >= FLOW_VALID_MIN)
    assert 0 < np.count_nonzero((from_list > 0) & (from_list < 1))  # a yaw and a sideways step: partial cells


def test_a_first_frame_has_no_flow_and_nothing_measured(client):
    first = client.post("/detect", json=detect_json("first", 1.0, FRAME, STILL)).json()
    assert first["frames_used"] == 1 and first["flow"] is None  # its window is copies of it: no real pair


def test_a_still_second_frame_is_valid_inside_the_crops_outer_ring(client):
    flow = second_answer(client, "still", STILL)["flow"]
    validity = validity_of(flow)
    ring = outer_ring(32)
    assert np.all(validity[ring] == 0.0)  # the outermost matching ring measures no motion at all
    assert np.all(validity[~ring] == 1.0) and np.all(validity[~ring] >= flow["validity_min"])
    encoded = validity_of(second_answer(client, "still-b64", STILL, fmt="base64")["flow"])
    np.testing.assert_array_equal(encoded, validity)  # 0 and 1 are exact in float16


def test_a_large_forward_motion_invalidates_the_front_band(client, runner):
    """8 m forward in 0.5 s (16 m/s) on a 22 m crop: the cells ahead held content beyond the previous crop."""
    forward = (0.0, 8.0, 0.0)
    flow = second_answer(client, "forward", forward)["flow"]
    validity = validity_of(flow)
    y = (16 - np.arange(32) - 0.5) * runner.config.cell_size  # row centres, metres forward
    edge = 0.5 * runner.config.input_size * runner.config.resolution - 0.5 * 4 * runner.config.resolution
    front = y + forward[1] >= edge  # rows whose content was beyond the previous crop's matching edge
    assert 8 <= front.sum() <= 14
    assert np.all(validity[front] == 0.0)
    seen = y + forward[1] <= edge - flow["search_reach_m"]  # rows seen before, the crop's back row among them
    assert np.all(validity[seen][:-1, 1:-1] == 1.0) and np.all(validity[-1] == 0.0)  # behind: the ring only
    np.testing.assert_array_equal(validity >= FLOW_VALID_MIN, expected_validity(runner, STILL, forward) >= 1.0)


def test_without_poses_the_validity_follows_odometrys_relative_pose(client, runner, odometry):
    first = client.post("/detect", json=detect_json("no-pose", 1.0, FRAME)).json()
    second = client.post("/detect", json=detect_json("no-pose", 1.5, FRAME)).json()
    assert second["pose_source"] == "odometry"
    poses = [[a["pose"][k] for k in ("x", "y", "yaw")] for a in (first, second)]
    exact = expected_validity(runner, *poses)  # the motion the model aligned the pair with (FakeOdometry's)
    validity = validity_of(second["flow"])
    np.testing.assert_array_equal(validity >= FLOW_VALID_MIN, exact >= FLOW_VALID_MIN)
    assert np.count_nonzero(validity < 1.0) > np.count_nonzero(outer_ring(32))  # moved: more than the ring


@pytest.mark.parametrize("fmt", ["list", "base64"])
def test_logs_and_the_live_view_draw_flow_arrows_only_on_valid_cells(client, fmt):
    """rafd.viz.mcap.frame_from_answer (rafd client's MCAP log, the live view's publisher) reads the answer's own
    validity in either form: every cell moves 1 m (the fake's flow y is the pose's x step), valid ones get arrows."""
    pytest.importorskip("foxglove", reason="MCAP logs and the live view need foxglove-sdk")
    from rafd.viz.mcap import answer_valid_cells, frame_from_answer

    answer = second_answer(client, f"logged-{fmt}", (1.0, 3.0, 0.05), fmt=fmt)
    valid = answer_valid_cells(answer["flow"])
    assert valid is not None and valid.shape == (32, 32)
    np.testing.assert_array_equal(valid, validity_of(answer["flow"]) >= FLOW_VALID_MIN)
    assert 0 < valid.sum() < valid.size - np.count_nonzero(outer_ring(32))  # moved: fewer than the inside
    frame = frame_from_answer(answer, b"", 128, 0.173611, FRAME, 0)
    assert frame.flow_heads is not None and len(frame.flow_heads) == valid.sum()
    cell = answer["flow"]["grid"]["cell_size_m"]
    rows = np.floor(16 - frame.flow_heads[:, 1] / cell).astype(int)  # y forward -> row from the top
    cols = np.floor(frame.flow_heads[:, 0] / cell + 16).astype(int)
    assert np.all(valid[rows, cols])


@pytest.fixture(scope="module")
def local_search_model(tmp_path_factory) -> Path:
    """A small random-weight ONNX step graph (64 px, 16 x 16 cells, 2 frames) with a local cost volume of radius 2:
    its flow geometry reaches the service only through the ONNX metadata's config."""
    pytest.importorskip("torch")
    from export.onnx_export import export_onnx
    from tests.utils.export_testing import make_checkpoint, small_config

    cfg = small_config(2)
    cfg = cfg.replace(flow=dataclasses.replace(cfg.flow, local_radius=2))
    root = tmp_path_factory.mktemp("flow_validity")
    return export_onnx(
        make_checkpoint(root / "model.pt", cfg), root / "step.onnx", verify=False, log=lambda _: None
    ).path


def test_an_onnx_models_search_reach_comes_from_its_metadata(local_search_model: Path):
    from rafd.runtime import OnnxRunner

    runner = OnnxRunner(local_search_model, threads=1)
    cfg = runner.config
    assert (cfg.flow.stride, cfg.flow.local_radius, cfg.feature_size) == (4, 2, 16)
    settings = Settings(threads=1, score_threshold=0.3)
    with TestClient(create_app(settings, runner=runner, odometry=FakeOdometry())) as client:
        wait_ready(client)
        frame = blob_frame(64, [(20, 30, 250)])
        client.post("/detect", json=detect_json("onnx", 1.0, frame, STILL))
        flow = client.post("/detect", json=detect_json("onnx", 1.5, frame, STILL)).json()["flow"]
    assert flow["search_reach_m"] == pytest.approx(2 * 4 * cfg.resolution, abs=1e-4)  # 2 matching cells
    validity = validity_of(flow)
    assert validity.shape == (16, 16)
    # still: the search window is cut at the crop's edge, 2 cells deep: 0 on the outer ring, half a reach inside it
    assert np.all(validity[outer_ring(16)] == 0.0)
    assert np.all(validity[1:-1, 1:-1][outer_ring(14)] == 0.5)
    assert np.all(validity[2:-2, 2:-2] == 1.0)
