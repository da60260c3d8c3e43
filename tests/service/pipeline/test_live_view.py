"""The Foxglove live view (`rafd serve --foxglove-port N`): a viewer connected over WebSocket receives every answered
frame in the MCAP logs' schemas, one topic prefix per stream, and the boxes equal the HTTP answer's; a full queue
drops frames (counted) instead of holding /detect; without foxglove-sdk the flag stops the service naming the extra."""

from __future__ import annotations

import math
import queue
import sys
import time
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
    # Connect only once the publisher has made the stream's channels: foxglove-sdk can refuse a subscription to a
    # channel created while the client was connecting ("subscribe to unknown channel"), a race of the library.
    deadline = time.monotonic() + 10.0
    while live._published.value < 1 and time.monotonic() < deadline:
        time.sleep(0.01)
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
    tracks = [b["track_id"].rsplit("-", 1)[1] for b in answer["boxes"]]
    assert labels == [f"{b['class']} {b['score']:.2f} #{t}" for b, t in zip(answer["boxes"], tracks)]


def test_a_full_queue_drops_frames_and_counts_them(live_client):
    live = live_client.app.state.live
    before = live.dropped._value.get()
    stopped = Settings(threads=1, foxglove_port=0, foxglove_queue_frames=1)
    from service.pipeline.live import LiveView

    idle = LiveView.from_settings(stopped)
    assert idle is not None
    idle._queue = queue.Queue(maxsize=1)  # the publisher's queue with no publisher draining it
    decoded = types.SimpleNamespace(odometry_view=None, covered=None, posted_size=128)
    idle.offer({"stream_id": "s"}, decoded)
    idle.offer({"stream_id": "s"}, decoded)  # returns at once: dropped, not waited for
    assert idle.dropped._value.get() == 1.0 and idle._queue.qsize() == 1
    assert live.dropped._value.get() == before  # the service's own live view dropped nothing
    metrics = live_client.get("/metrics").text
    assert "rafd_live_view_published " in metrics and "rafd_live_view_dropped_total" in metrics


def test_without_foxglove_the_flag_names_the_extra(monkeypatch, capsys, tmp_path):
    from service.cli import main
    from service.pipeline.live import LiveView

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


# ---------------------------------------------------------------- who sees what (issue 40, finding 2)
ALICE, BOB = "alice:alice-key-0123456789abcdef", "bob:bob-key-0123456789abcdef01"
AS_ALICE, AS_BOB = {"X-API-Key": ALICE.split(":")[1]}, {"X-API-Key": BOB.split(":")[1]}


def test_with_api_keys_the_live_view_must_name_the_one_key_it_shows():
    pytest.importorskip("foxglove", reason="foxglove-sdk is not installed (the live extra)")
    from service.pipeline.live import LiveView

    with pytest.raises(ValueError, match="RAFD_FOXGLOVE_KEY"):
        create_app(Settings(threads=1, foxglove_port=0, api_keys=[ALICE, BOB]), runner=FakeRunner())
    with pytest.raises(ValueError, match="names no configured API key"):
        create_app(Settings(threads=1, foxglove_port=0, api_keys=[ALICE], foxglove_key="carol"), runner=FakeRunner())
    with pytest.raises(ValueError, match="no API keys are configured"):
        LiveView.from_settings(Settings(threads=1, foxglove_port=0, foxglove_key="alice"))
    shown = LiveView.from_settings(Settings(threads=1, foxglove_port=0, foxglove_key="alice"), key_names=("alice",))
    assert shown is not None and shown.key == "alice"


def test_only_the_shown_keys_answers_leave_the_service():
    """Another key's answer is never queued for the publisher (so never advertised nor merged), nor counted dropped."""
    pytest.importorskip("foxglove", reason="foxglove-sdk is not installed (the live extra)")
    from service.pipeline.live import LiveView

    live = LiveView("127.0.0.1", 0, 4, key="alice")
    live._queue = queue.Queue(maxsize=4)  # no publisher: only what is offered
    decoded = types.SimpleNamespace(odometry_view=None, covered=None, posted_size=128)
    live.offer({"stream_id": "car-2", "pose": "bob's"}, decoded, "bob")
    live.offer({"stream_id": "car-2", "pose": "alice's"}, decoded, "alice")
    live.offer({"stream_id": "car-3"}, decoded, None)
    assert live._queue.qsize() == 1 and live._queue.get_nowait()[0]["pose"] == "alice's"
    assert live.dropped._value.get() == 0.0


def test_a_viewer_sees_only_the_shown_keys_streams_never_merged_with_anothers():
    """The finding: `/car-2/*` carried key A's and key B's poses alternately, and B's stream ids were advertised.
    Now, with the view showing alice's streams, bob's `car-2` and `bob-only` never reach the viewer."""
    pytest.importorskip("foxglove", reason="foxglove-sdk is not installed (the live extra)")
    pytest.importorskip("websockets", reason="websockets is not installed (the dev extra)")
    from tests.utils.foxglove_testing import Viewer

    frame = blob_frame(128, [(40, 60, 250)])
    settings = Settings(threads=1, score_threshold=0.3, foxglove_port=0, api_keys=[ALICE, BOB], foxglove_key="alice")
    with TestClient(create_app(settings, runner=FakeRunner(), odometry=FakeOdometry())) as client:
        wait_ready(client)

        def post(stream: str, t: float, x: float, headers: dict[str, str]) -> None:
            response = client.post("/detect", json=detect_json(stream, t, frame, (x, 0.0, 0.0)), headers=headers)
            assert response.status_code == 200, response.text

        post("car-2", 1.0, 1.0, AS_ALICE)
        post("car-2", 1.0, 50.0, AS_BOB)
        post("bob-only", 1.0, 0.0, AS_BOB)
        post("alice-marker", 1.0, 0.0, AS_ALICE)  # published after everything above (one FIFO queue)
        viewer = Viewer(client.app.state.live.port)
        try:
            viewer.wait_for_topic("/alice-marker/tf")
            assert not [topic for topic in viewer.channels if "bob-only" in topic]
            tf = viewer.subscribe("/car-2/tf")
            post("car-2", 2.0, 2.0, AS_ALICE)
            post("car-2", 2.0, 60.0, AS_BOB)
            post("car-2", 3.0, 3.0, AS_ALICE)
            seen: list[float] = []
            for _ in range(6):  # bounded: the two frames of alice's, maybe her first one again
                seen.append(round(viewer.next_message(tf).translation.x, 6))
                if seen[-1] == 3.0:
                    break
        finally:
            viewer.close()
    assert seen[-1] == 3.0 and 2.0 in seen
    assert set(seen) <= {1.0, 2.0, 3.0}, seen  # never bob's 50 or 60
