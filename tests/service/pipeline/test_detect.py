"""POST /detect happy paths: answers equal the runner's output, decoded; polygons, flow, warm-up, poses."""

from __future__ import annotations

import base64
import json
from dataclasses import replace

import numpy as np
import pytest
from fastapi.testclient import TestClient

from rafd.detections import decode_detections
from rafd.geometry import box_polygons_pixels, compose_poses
from service.app import create_app
from tests.utils.answers_testing import chain_free
from tests.utils.fake_runner import FakeRunner
from tests.utils.service_testing import (
    FakeOdometry,
    blob_frame,
    detect_json,
    png,
    stream_state,
    wait_ready,
    wait_until,
)

FRAMES = [blob_frame(128, [(8 + 4 * t, 16, 250), (64, 40 + 4 * t, 120), (100, 100, 90)]) for t in range(6)]
POSES = [(1.0 * t, 0.5 * t, 0.05 * t) for t in range(6)]


def offline(frames, poses):
    """The FakeRunner run directly on the stream's frames: what the service must answer."""
    runner, state, results = FakeRunner(), None, []
    state = runner.new_state()
    for frame, pose in zip(frames, poses):
        result, state = runner.step(state, (frame.astype(np.float32) / 255.0)[None], np.asarray(pose)[None])
        results.append(result.view(0))
    return results


def assert_boxes_match(answer_boxes, result, posted_size, threshold=0.3):
    expected = decode_detections(result.boxes, result.scores, threshold)
    assert len(answer_boxes) == len(expected) > 0
    got = np.array([[b["x"], b["y"], b["width"], b["length"], b["yaw"]] for b in answer_boxes])
    np.testing.assert_allclose(got, expected.boxes, atol=1e-4)
    np.testing.assert_allclose([b["score"] for b in answer_boxes], expected.scores, atol=1e-5)
    polygons = np.array([b["polygon"] for b in answer_boxes])
    np.testing.assert_allclose(polygons, box_polygons_pixels(expected.boxes, posted_size), atol=0.01)
    assert {b["class"] for b in answer_boxes} == {"vehicle"}


def test_json_stream_warms_up_then_uses_full_window(client):
    expected = offline(FRAMES, POSES)
    for t, (frame, pose) in enumerate(zip(FRAMES, POSES)):
        response = client.post("/detect", json=detect_json("car-1", 100.0 + t, frame, pose))
        assert response.status_code == 200, response.text
        answer = response.json()
        assert answer["frames_used"] == min(t + 1, 4)
        assert answer["warming_up"] is (t < 3)
        assert answer["pose_source"] == "request"
        assert answer["pose"] == pytest.approx({"x": pose[0], "y": pose[1], "yaw": pose[2]})
        assert answer["input"] == {
            "posted_size": 128,
            "model_size": 128,
            "posted_format": "cartesian",
            "covered": {"side_px": 128, "offset_px": 0, "side_m": 22.222, "range_m": None, "tiles": 1},
        }
        assert answer["model"]["version"] == "fake-1"
        stages = ("read_ms", "decode_ms", "wait_ms", "odometry_ms", "model_ms", "post_ms")
        assert set(answer["timing"]) == {*stages, "total_ms"}
        assert sum(answer["timing"][k] for k in stages) == pytest.approx(answer["timing"]["total_ms"], abs=0.004)
        assert_boxes_match(answer["boxes"], expected[t], 128)
        if t == 0:
            assert answer["flow"] is None  # no real pair on a stream's first frame
        else:
            flow = answer["flow"]
            assert flow["shape"] == [2, 32, 32] and flow["units"] == "m" and flow["encoding"] == "list"
            assert flow["pair"] == [100.0 + t - 1, 100.0 + t]
            np.testing.assert_allclose(np.array(flow["values"]), expected[t].flow, atol=5e-4)


def test_a_range_within_the_models_crop_detects_over_that_crop_and_polygons_use_the_scans_pixels(settings, runner):
    crop = FRAMES[0]
    scan = np.zeros((1152, 1152), np.uint8)
    scan[512:640, 512:640] = crop  # the model's 128 crop around the radar at (576, 576)
    scan[0:50, 0:50] = 255  # outside the crop: must not matter
    near = settings.model_copy(update={"detect_range_m": 10.0})
    with TestClient(create_app(near, runner=runner, odometry=FakeOdometry())) as client:
        wait_ready(client)
        from_scan = client.post("/detect", json=detect_json("scan", 1.0, scan, POSES[0])).json()
        from_crop = client.post("/detect", json=detect_json("crop", 1.0, crop, POSES[0])).json()
        second = client.post("/detect", json=detect_json("scan", 2.0, scan, POSES[1])).json()
    assert from_scan["input"] == {
        "posted_size": 1152,
        "model_size": 128,
        "posted_format": "cartesian",
        "covered": {"side_px": 128, "offset_px": 512, "side_m": 22.222, "range_m": 10.0, "tiles": 1},
    }
    assert [b["score"] for b in from_scan["boxes"]] == [b["score"] for b in from_crop["boxes"]]
    scan_polygons = np.array([b["polygon"] for b in from_scan["boxes"]])
    crop_polygons = np.array([b["polygon"] for b in from_crop["boxes"]])
    np.testing.assert_allclose(scan_polygons, crop_polygons + 512, atol=0.011)
    expected = offline([crop], POSES[:1])[0]
    inside = np.hypot(*expected.boxes[:, :2].T) <= 10.0  # the range cuts the crop's corners off
    assert_boxes_match(
        from_scan["boxes"], replace(expected, boxes=expected.boxes[inside], scores=expected.scores[inside]), 1152
    )
    assert second["flow"]["grid"]["origin_px"] == [512, 512]
    assert second["flow"]["grid"]["stride_px"] == 4 and second["flow"]["shape"] == [2, 32, 32]


def test_a_full_scan_is_detected_over_the_whole_scan(client):
    """A vehicle 79 m ahead, far outside the model's crop, is found where it is; the answer says what was covered
    and the flow covers the whole scan."""
    scan = np.zeros((1152, 1152), np.uint8)
    scan[120:124, 574:578] = 255  # 4 x 4 px centred 454 px ahead of the radar: y = 454 * 0.173611 m
    first = client.post("/detect", json=detect_json("whole", 1.0, scan, POSES[0]))
    assert first.status_code == 200, first.text
    answer = first.json()
    covered = answer["input"]["covered"]
    assert covered["side_px"] == 1152 and covered["offset_px"] == 0 and covered["range_m"] is None
    assert covered["tiles"] > 100  # the tiny model's 128 px tiles
    boxes = np.array([[b["x"], b["y"]] for b in answer["boxes"]])
    assert len(boxes) and np.hypot(boxes[:, 0], boxes[:, 1] - 454 * 0.173611).min() < 0.7  # one cell
    polygon = np.array(answer["boxes"][0]["polygon"]).mean(0)  # the best box: the vehicle, in the scan's pixels
    assert np.abs(polygon - [576.0, 122.0]).max() < 4.0
    second = client.post("/detect", json=detect_json("whole", 2.0, scan, POSES[1])).json()
    assert second["flow"]["shape"] == [2, 288, 288] and second["flow"]["grid"]["origin_px"] == [0, 0]
    cost = client.get("/model").json()["full_scan"]  # what a full scan costs, from the two served
    assert cost["side_px"] == 1152 and cost["tiles"] == covered["tiles"] and cost["frames"] == 2
    held = stream_state(client, "whole")["state_bytes"]  # the model's state and the tracks' (a few kB)
    assert cost["model_ms"] > 0 and 0 <= held - cost["state_bytes"] < 100_000


def test_multipart_gives_the_same_answer_as_json(client):
    for t in range(3):
        files = {"image": ("frame.png", png(FRAMES[t]), "image/png")}
        data = {
            "stream_id": "form",
            "timestamp": str(10.0 + t),
            "pose_x": str(POSES[t][0]),
            "pose_y": str(POSES[t][1]),
            "pose_yaw": str(POSES[t][2]),
        }
        form = client.post("/detect", data=data, files=files)
        assert form.status_code == 200, form.text
        js = client.post("/detect", json=detect_json("json", 10.0 + t, FRAMES[t], POSES[t])).json()
        assert chain_free(form.json()["boxes"]) == chain_free(js["boxes"])
        for key in ("flow", "frames_used", "pose", "pose_source"):
            assert form.json()[key] == js[key]


def test_flow_can_be_left_out_or_sent_as_base64_float16(client):
    expected = offline(FRAMES[:2], POSES[:2])[1].flow
    client.post("/detect", json=detect_json("f", 1.0, FRAMES[0], POSES[0]))
    client.post("/detect", json=detect_json("g", 1.0, FRAMES[0], POSES[0]))
    assert client.post("/detect?flow=false", json=detect_json("f", 2.0, FRAMES[1], POSES[1])).json()["flow"] is None
    flow = client.post("/detect?flow_format=base64", json=detect_json("g", 2.0, FRAMES[1], POSES[1])).json()["flow"]
    assert flow["encoding"] == "base64-float16"
    values = np.frombuffer(base64.b64decode(flow["values"]), "<f2").reshape(flow["shape"])
    np.testing.assert_allclose(values, expected, rtol=1e-3, atol=1e-3)


def test_without_pose_the_service_uses_odometry_composed_onto_the_last_pose(client, odometry):
    answers = [client.post("/detect", json=detect_json("odo", float(t), FRAMES[t])).json() for t in range(3)]
    assert [a["pose_source"] for a in answers] == ["odometry"] * 3
    expected_pose = np.zeros(3)
    for t, answer in enumerate(answers):
        if t:
            expected_pose = compose_poses(expected_pose, odometry.motion)
        np.testing.assert_allclose([answer["pose"][k] for k in ("x", "y", "yaw")], expected_pose, atol=1e-6)
    # Odometry saw (previous crop, current crop) at the model's resolution.
    assert len(odometry.calls) == 2
    np.testing.assert_array_equal(odometry.calls[1][0], FRAMES[1])
    np.testing.assert_array_equal(odometry.calls[1][1], FRAMES[2])
    # The runner got those poses: the fake's yaw is newest yaw - oldest yaw of its window.
    assert answers[2]["boxes"][0]["yaw"] == pytest.approx(2 * odometry.motion[2], abs=1e-5)


def test_odometry_registers_the_centre_512_px_of_a_full_scan_and_a_size_switch_starts_a_new_chain(client, odometry):
    """Odometry registers the centre 512 px of full scans; a frame of another size is detected over another view, so
    it starts a new chain (the model's state is per tile), and says so."""
    rng = np.random.default_rng(3)
    scans = [rng.integers(0, 255, (1152, 1152), dtype=np.uint8) for _ in range(2)]
    for t, scan in enumerate(scans):
        assert client.post("/detect", json=detect_json("wide", float(t), scan)).status_code == 200
    previous, current, _ = odometry.calls[-1]
    np.testing.assert_array_equal(previous, scans[0][320:832, 320:832])
    np.testing.assert_array_equal(current, scans[1][320:832, 320:832])
    calls = len(odometry.calls)
    switched = client.post("/detect", json=detect_json("wide", 2.0, FRAMES[0]))
    assert switched.status_code == 200, switched.text
    answer = switched.json()
    assert answer["stream_restarted"] == "view_changed" and answer["frames_used"] == 1
    assert answer["pose"] == {"x": 0.0, "y": 0.0, "yaw": 0.0} and len(odometry.calls) == calls


def test_pose_mixing_rule(client, odometry):
    # Started with request poses: a frame without pose continues from the last pose by odometry.
    client.post("/detect", json=detect_json("gps", 1.0, FRAMES[0], (10.0, 20.0, 0.3)))
    gap = client.post("/detect", json=detect_json("gps", 2.0, FRAMES[1])).json()
    assert gap["pose_source"] == "odometry"
    np.testing.assert_allclose(
        [gap["pose"][k] for k in ("x", "y", "yaw")],
        compose_poses(np.array([10.0, 20.0, 0.3]), odometry.motion),
        atol=1e-6,
    )
    back = client.post("/detect", json=detect_json("gps", 3.0, FRAMES[2], (11.0, 21.0, 0.4)))
    assert back.status_code == 200 and back.json()["pose_source"] == "request"
    # Started without poses: a request pose would live in another world frame -> 409, nothing changes.
    client.post("/detect", json=detect_json("odo", 1.0, FRAMES[0]))
    before = client.get("/streams").json()
    conflict = client.post("/detect", json=detect_json("odo", 2.0, FRAMES[1], (1.0, 2.0, 0.0)))
    assert conflict.status_code == 409
    assert conflict.json()["error"]["code"] == "pose_source_conflict"
    after = client.get("/streams").json()
    strip = lambda body: [{k: v for k, v in s.items() if k != "idle_s"} for s in body["streams"]]  # noqa: E731
    assert strip(after) == strip(before)


def test_score_threshold_setting_filters_boxes(settings):
    settings.score_threshold = 0.6
    with TestClient(create_app(settings, runner=FakeRunner())) as client:
        wait_ready(client)
        answer = client.post("/detect", json=detect_json("t", 1.0, FRAMES[0], POSES[0])).json()
    assert answer["boxes"] and all(b["score"] >= 0.6 for b in answer["boxes"])
    assert_boxes_match(answer["boxes"], offline(FRAMES[:1], POSES[:1])[0], 128, threshold=0.6)


def test_real_odometry_on_the_radiate_sample(radiate_sample, settings):
    """With no odometry injected the service uses rafd.odometry.registration (when that module is present)."""
    pytest.importorskip("rafd.odometry.registration")
    scans = sorted((radiate_sample / "Navtech_Cartesian").glob("*.png"))[:3]
    with TestClient(create_app(settings, runner=FakeRunner())) as client:
        wait_ready(client)
        answers = []
        for t, path in enumerate(scans):
            body = {"stream_id": "real", "timestamp": float(t), "image": base64.b64encode(path.read_bytes()).decode()}
            response = client.post("/detect", json=body)
            assert response.status_code == 200, response.text
            answers.append(response.json())
    assert [a["pose_source"] for a in answers] == ["odometry"] * 3
    assert answers[0]["pose"] == {"x": 0.0, "y": 0.0, "yaw": 0.0}
    assert all(np.isfinite(list(a["pose"].values())).all() for a in answers)


class FailingRunner(FakeRunner):
    """Fails on frames whose top-left pixel is 7 (the model breaking on one frame)."""

    def step(self, state, frames, poses):
        if round(float(frames[0, 0, 0]) * 255) == 7:
            raise RuntimeError("onnxruntime failed")
        return super().step(state, frames, poses)


def test_a_model_failure_answers_500_and_changes_no_stream(settings):
    broken = FRAMES[1].copy()
    broken[0, 0] = 7
    app = create_app(settings, runner=FailingRunner())
    with TestClient(app, raise_server_exceptions=False) as client:
        wait_ready(client)
        assert client.post("/detect", json=detect_json("ok", 1.0, FRAMES[0], POSES[0])).status_code == 200
        before = client.get("/streams").json()["streams"]
        failed = client.post("/detect", json=detect_json("ok", 2.0, broken, POSES[1]))
        assert failed.status_code == 500 and failed.json()["error"]["code"] == "internal_error"
        assert client.post("/detect", json=detect_json("new", 1.0, broken, POSES[0])).status_code == 500
        after = client.get("/streams").json()["streams"]
        assert [{k: v for k, v in s.items() if k != "idle_s"} for s in after] == [
            {k: v for k, v in s.items() if k != "idle_s"} for s in before
        ]  # "new" was not created either
        retry = client.post("/detect", json=detect_json("ok", 2.0, FRAMES[1], POSES[1])).json()
        assert retry["frames_used"] == 2  # the failed frame never entered the buffer


def test_the_stream_can_be_named_in_a_header_or_the_path(client):
    """X-Stream-Id and POST /streams/{id}/detect (for routing without reading the body) answer like the body."""
    for t in range(3):
        body = detect_json("body", 10.0 + t, FRAMES[t], POSES[t])
        by_body = client.post("/detect", json=body).json()
        anonymous = {k: v for k, v in body.items() if k != "stream_id"}
        by_header = client.post("/detect", json=anonymous, headers={"X-Stream-Id": "header"}).json()
        by_path = client.post("/streams/path/detect", json=anonymous).json()
        both = client.post(
            "/streams/both/detect", json=body | {"stream_id": "both"}, headers={"X-Stream-Id": "both"}
        ).json()
        files = {"image": ("frame.png", png(FRAMES[t]), "image/png")}
        form = client.post(
            "/streams/form/detect",
            files=files,
            data={
                "timestamp": str(10.0 + t),
                "pose_x": str(POSES[t][0]),
                "pose_y": str(POSES[t][1]),
                "pose_yaw": str(POSES[t][2]),
            },
        ).json()
        for answer, name in ((by_header, "header"), (by_path, "path"), (both, "both"), (form, "form")):
            assert answer["stream_id"] == name
            assert chain_free(answer["boxes"]) == chain_free(by_body["boxes"]), name
            for key in ("flow", "frames_used", "pose"):
                assert answer[key] == by_body[key], (name, key)
    assert {s["stream_id"] for s in client.get("/streams").json()["streams"]} == {
        "body",
        "header",
        "path",
        "both",
        "form",
    }


@pytest.mark.parametrize(
    "metadata, setting, expected",
    [
        ({}, None, 0.3),  # a model without an operating threshold: 0.3
        ({"operating_threshold": "0.55"}, None, 0.55),  # the model's own
        ({"operating_threshold": "0.55"}, 0.2, 0.2),  # RAFD_SCORE_THRESHOLD wins
    ],
)
def test_score_threshold_is_the_models_operating_threshold_unless_set(settings, metadata, setting, expected):
    settings.score_threshold = setting
    runner = FakeRunner()
    runner.metadata.update(metadata)
    with TestClient(create_app(settings, runner=runner)) as client:
        wait_ready(client)
        assert client.get("/model").json()["score_threshold"] == expected
        answer = client.post("/detect", json=detect_json("t", 1.0, FRAMES[0], POSES[0])).json()
    assert all(b["score"] >= expected for b in answer["boxes"])
    assert_boxes_match(answer["boxes"], offline(FRAMES[:1], POSES[:1])[0], 128, threshold=expected)


@pytest.mark.parametrize("value", ["high", "1.5"])
def test_a_bad_operating_threshold_in_the_model_is_an_error_at_start_up(value):
    """The model does not load (readiness says why) rather than answering at a threshold nobody chose."""
    from service.settings import Settings

    runner = FakeRunner()
    runner.metadata["operating_threshold"] = value
    with TestClient(create_app(Settings(threads=1), runner=runner)) as client:
        wait_until(lambda: "failed to load" in client.get("/health/ready").text, message="the load to fail")
        ready = client.get("/health/ready")
    assert ready.status_code == 503 and "operating_threshold" in ready.json()["error"]["message"]


def test_flow_list_is_written_as_the_same_text_as_nested_lists():
    """The route lets orjson write the rounded flow array itself (service.pipeline.detector._flow): it must give the
    very text of the nested lists the answer promised, -0.0, whole numbers and large values included."""
    import orjson

    rng = np.random.default_rng(0)
    flow = np.concatenate([rng.normal(0, 2, 2 * 64 * 64 - 6), [-0.0001, 0.0004999, 3.0, -250.1234, 1e-9, 0.0005]])
    values = np.round(flow.reshape(2, 64, 64).astype(np.float32).astype(np.float64), 3)
    assert orjson.dumps({"values": values}, option=orjson.OPT_SERIALIZE_NUMPY) == orjson.dumps(
        {"values": values.tolist()}
    )


def test_a_models_far_threshold_is_answered_at_each_boxs_range_and_reported(settings):
    from rafd.detections import answered
    from rafd.protocol import OperatingThreshold

    result = offline(FRAMES[:1], POSES[:1])[0]
    expected_all = decode_detections(result.boxes, result.scores, 0.3)
    ranges = np.hypot(*expected_all.boxes[:, :2].T)
    from_m = float(np.median(ranges))  # about half the fake's boxes lie beyond it
    rule = OperatingThreshold(0.3, far=0.99, far_from_m=from_m)
    kept = answered(expected_all.as_array(), rule)
    assert 0 < len(kept) < len(expected_all)  # the far threshold drops something here
    settings.score_threshold = None  # the model's own
    runner = FakeRunner()
    runner.metadata.update(
        {"operating_threshold": "0.3", "operating_threshold_far": json.dumps({"from_m": from_m, "threshold": 0.99})}
    )
    with TestClient(create_app(settings, runner=runner)) as client:
        wait_ready(client)
        info = client.get("/model").json()
        answer = client.post("/detect", json=detect_json("far", 1.0, FRAMES[0], POSES[0])).json()
    assert info["score_threshold"] == 0.3 and info["far_score_threshold"] == {"from_m": from_m, "threshold": 0.99}
    got = np.array([[b["x"], b["y"], b["width"], b["length"], b["yaw"], b["score"]] for b in answer["boxes"]])
    np.testing.assert_allclose(got, kept, atol=1e-4)
