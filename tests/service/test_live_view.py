"""The Foxglove live view (`rafd serve --foxglove-port N`): a viewer connected over WebSocket receives every answered
frame in the MCAP logs' schemas, one topic prefix per stream, and the boxes equal the HTTP answer's; a full queue
drops frames (counted) instead of holding /detect; without foxglove-sdk the flag stops the service naming the extra."""

from __future__ import annotations

import math
import queue
import sys
import types

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.settings import Settings
from tests.utils.fake_runner import FakeRunner
from tests.utils.service_testing import FakeOdometry, blob_frame, detect_json, wait_ready

pytestmark = pytest.mark.network


@pytest.fixture
def live_client():
    pytest.importorskip("foxglove", reason="foxglove-sdk is not installed (the live extra)")
    pytest.importorskip("websockets", reason="websockets is not installed (the dev extra)")
    settings = Settings(threads=1, score_threshold=0.3, foxglove_port=0)
    with TestClient(create_app(settings, runner=FakeRunner(), odometry=FakeOdometry())) as client:
        wait_ready(client)
        yield client


def test_a_viewer_receives_the_boxes_of_the_http_answer(live_client):
    from tests.utils.foxglove_testing import Viewer

    live = live_client.app.state.live
    assert live is not None and live.port
    frame = blob_frame(128, [(40, 60, 250), (90, 20, 180)])
    first = live_client.post("/detect", json=detect_json("car-1", 1.0, frame, (0.0, 0.0, 0.0)))
    assert first.status_code == 200
    viewer = Viewer(live.port)
    try:
        # the stream's channels, in the MCAP logs' schemas, under its own prefix
        detections = viewer.subscribe("/car-1/radar/detections")
        assert viewer.channels["/car-1/radar/detections"]["schemaName"] == "foxglove.SceneUpdate"
        assert viewer.wait_for_topic("/car-1/radar/scan")["schemaName"] == "foxglove.CompressedImage"
        assert viewer.wait_for_topic("/car-1/tf")["schemaName"] == "foxglove.FrameTransform"
        assert viewer.wait_for_topic("/car-1/radar/flow")["schemaName"] == "foxglove.SceneUpdate"
        answer = live_client.post("/detect", json=detect_json("car-1", 2.0, frame, (0.5, 1.0, 0.1))).json()
        update = viewer.next_message(detections)
        if update.deletions[0].timestamp.seconds == 1:  # the first frame, published after the subscription
            update = viewer.next_message(detections)
    finally:
        viewer.close()
    assert update.deletions[0].timestamp.seconds == 2  # the frame of this answer (stamped with its timestamp)
    assert answer["boxes"], "the fake runner answers boxes above 0.3 for bright blobs"
    cubes = [entity.cubes[0] for entity in update.entities]
    assert len(cubes) == len(answer["boxes"])
    for cube, box in zip(cubes, answer["boxes"]):
        assert math.isclose(cube.pose.position.x, box["x"], abs_tol=1e-9)
        assert math.isclose(cube.pose.position.y, box["y"], abs_tol=1e-9)
        assert math.isclose(cube.size.x, box["width"], abs_tol=1e-9)
        assert math.isclose(cube.size.y, box["length"], abs_tol=1e-9)
        yaw = 2 * math.atan2(cube.pose.orientation.z, cube.pose.orientation.w)
        assert math.isclose(math.remainder(yaw - box["yaw"], 2 * math.pi), 0.0, abs_tol=1e-9)
    labels = [entity.metadata[0].value for entity in update.entities]
    assert labels == [f"{b['class']} {b['score']:.2f}" for b in answer["boxes"]]


def test_a_full_queue_drops_frames_and_counts_them(live_client):
    live = live_client.app.state.live
    before = live.dropped._value.get()
    stopped = Settings(threads=1, foxglove_port=0, foxglove_queue_frames=1)
    from service.live import LiveView

    idle = LiveView.from_settings(stopped)
    assert idle is not None
    idle._queue = queue.Queue(maxsize=1)  # the publisher's queue with no publisher draining it
    decoded = types.SimpleNamespace(odometry_view=None, crop=None, posted_size=128)
    idle.offer({"stream_id": "s"}, decoded)
    idle.offer({"stream_id": "s"}, decoded)  # returns at once: dropped, not waited for
    assert idle.dropped._value.get() == 1.0 and idle._queue.qsize() == 1
    assert live.dropped._value.get() == before  # the service's own live view dropped nothing
    metrics = live_client.get("/metrics").text
    assert "rafd_live_view_published " in metrics and "rafd_live_view_dropped_total" in metrics


def test_without_foxglove_the_flag_names_the_extra(monkeypatch, capsys, tmp_path):
    from service.cli import main
    from service.live import LiveView

    monkeypatch.setitem(sys.modules, "foxglove", None)  # import foxglove -> ImportError
    with pytest.raises(ValueError, match=r"pip install 'rafd\[live\]'"):
        LiveView.from_settings(Settings(threads=1, foxglove_port=0))
    model = tmp_path / "model.onnx"
    model.write_bytes(b"\x08\x08\x12\x07pytorch")  # the start of an ONNX file is enough before the app starts
    assert main(["--model", str(model), "--foxglove-port", "8765"]) == 2
    err = capsys.readouterr().err
    assert "rafd[live]" in err and "--foxglove-port" in err


def test_the_live_view_is_off_by_default(client):
    assert client.app.state.live is None
    assert "rafd_live_view" not in client.get("/metrics").text
