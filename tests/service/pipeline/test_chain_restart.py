"""Issue 39, items 1 and 3: a chain is never silently stale, and a frame posted again after a lost answer is safe.

- A timestamp gap over RAFD_STREAM_GAP_RESTART_S, or a `previous_timestamp` that is not the chain's last frame,
  restarts the stream's buffer (`frames_used` 1, `warming_up` true, `stream_restarted` with the reason) and its
  odometry world frame, in JSON and multipart requests; one or two dropped frames do not.
- The same frame again (same stream, timestamp, image and pose) gets the same answer, `replayed: true`, and does not
  change the stream or run the model; the same timestamp with another image is still refused (409).
The issue's reproduction: frames 1-8 to a replica, 9-12 elsewhere, 13-16 back: frame 13 must not be stacked on 6-8.
"""

from __future__ import annotations

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.schemas import DetectResponse
from service.settings import Settings
from tests.utils.fake_runner import FakeRunner
from tests.utils.service_testing import FakeOdometry, blob_frame, detect_json, png, stream_state, wait_ready

PERIOD = 0.25  # a 4 Hz radar


def frame(i: int) -> np.ndarray:
    return blob_frame(128, [(8 + i, 8, 255)])


def post(client: TestClient, i: int, previous: int | None = None, stream: str = "car", **changes) -> dict:
    body = detect_json(stream, i * PERIOD, frame(i))
    if previous is not None:
        body["previous_timestamp"] = previous * PERIOD
    body.update(changes)
    response = client.post("/detect", json=body, headers={"X-Stream-Id": stream})
    assert response.status_code == 200, response.text
    answer = response.json()
    DetectResponse.model_validate(answer)  # the contract: every field declared
    return answer


@pytest.fixture
def app_parts():
    runner, odometry = FakeRunner(), FakeOdometry()
    settings = Settings(threads=1)  # the defaults: RAFD_STREAM_GAP_RESTART_S = 1.0
    with TestClient(create_app(settings, runner=runner, odometry=odometry)) as client:
        wait_ready(client)
        yield client, runner, odometry


def test_the_issue_s_returning_stream_restarts_by_previous_timestamp(app_parts):
    client, _, odometry = app_parts
    answers = [post(client, i, previous=i - 1 if i > 1 else None) for i in range(1, 9)]
    assert answers[-1]["frames_used"] == 4 and "stream_restarted" not in answers[-1]
    moving_pose = answers[-1]["pose"]
    assert np.hypot(moving_pose["x"], moving_pose["y"]) > 10.0  # FakeOdometry: about 2 m per frame, 7 steps
    # frames 9-12 went to another replica; frame 13 comes back, 5 periods (1.25 s) after frame 8
    back = post(client, 13, previous=12)
    assert back["frames_used"] == 1 and back["warming_up"] is True
    assert back["stream_restarted"] == "gap"  # 1.25 s > 1.0 s: the gap alone already tells
    assert back["pose"] == {"x": 0.0, "y": 0.0, "yaw": 0.0}  # the odometry world frame restarts here
    assert back["flow"] is None
    following = post(client, 14, previous=13)
    assert following["frames_used"] == 2 and "stream_restarted" not in following
    assert following["flow"]["pair"] == [13 * PERIOD, 14 * PERIOD]


def test_a_short_failover_is_caught_by_previous_timestamp_alone(app_parts):
    client, _, _ = app_parts
    for i in range(1, 6):
        post(client, i, previous=i - 1 if i > 1 else None)
    generation = stream_state(client, "car")["generation"]
    # frames 6 and 7 went elsewhere; frame 8 is 0.75 s after frame 5, within the gap rule
    back = post(client, 8, previous=7)
    assert back["frames_used"] == 1 and back["stream_restarted"] == "previous_timestamp_mismatch"
    state = stream_state(client, "car")
    assert state["generation"] > generation and state["frames_buffered"] == 1 and state["last_timestamp"] == 2.0


def test_dropped_frames_within_the_gap_keep_the_chain(app_parts):
    client, _, _ = app_parts
    post(client, 1)
    post(client, 2, previous=1)
    kept = post(client, 5, previous=2)  # frames 3 and 4 never arrived anywhere: 0.75 s
    assert kept["frames_used"] == 3 and "stream_restarted" not in kept
    without_field = post(client, 8)  # another 0.75 s, no previous_timestamp: only the gap rule
    assert without_field["frames_used"] == 4 and "stream_restarted" not in without_field


def test_a_gap_restarts_without_the_field_and_the_setting_turns_it_off():
    for limit, restarts in ((1.0, True), (0.0, False)):
        settings = Settings(threads=1, stream_gap_restart_s=limit)
        with TestClient(create_app(settings, runner=FakeRunner(), odometry=FakeOdometry())) as client:
            wait_ready(client)
            post(client, 1)
            post(client, 2)
            late = post(client, 7)  # 1.25 s later
            assert ("stream_restarted" in late) is restarts
            assert late["frames_used"] == (1 if restarts else 3)


def test_multipart_takes_previous_timestamp(app_parts):
    client, _, _ = app_parts
    post(client, 1)
    post(client, 2)

    def form(i: int, previous: int) -> dict:
        fields = {"stream_id": "car", "timestamp": str(i * PERIOD), "previous_timestamp": str(previous * PERIOD)}
        return client.post(
            "/detect",
            files=[*((k, (None, v)) for k, v in fields.items()), ("image", ("f.png", png(frame(i)), "image/png"))],
        ).json()

    assert form(3, 2)["frames_used"] == 3
    mismatch = form(4, 1)
    assert mismatch["frames_used"] == 1 and mismatch["stream_restarted"] == "previous_timestamp_mismatch"


@pytest.mark.parametrize(
    "previous, message",
    [(2.0, "must be before timestamp"), (3.0, "must be before timestamp"), ("1.0", "valid number")],
)
def test_a_previous_timestamp_not_before_the_frame_is_refused(app_parts, previous, message):
    client, _, _ = app_parts
    body = {**detect_json("car", 2.0, frame(1)), "previous_timestamp": previous}
    response = client.post("/detect", json=body)
    assert response.status_code == 422 and message in response.json()["error"]["message"]
    assert stream_state(client, "car") is None  # refused: no stream made


def test_the_same_frame_again_is_answered_again_without_a_model_run(app_parts):
    client, runner, odometry = app_parts
    post(client, 1)
    first = post(client, 2, previous=1)
    calls, odometry_calls, state = runner.calls, len(odometry.calls), stream_state(client, "car")
    again = post(client, 2, previous=1)  # the answer was lost: the client posts the frame again
    assert again.pop("replayed") is True
    assert again == first  # the same answer, timing included
    assert runner.calls == calls and len(odometry.calls) == odometry_calls
    assert stream_state(client, "car") == state
    after = post(client, 3, previous=2)  # the chain goes on as if the frame had come once
    assert after["frames_used"] == 3 and "replayed" not in after


def test_the_same_timestamp_with_another_image_or_pose_is_refused(app_parts):
    client, _, _ = app_parts
    post(client, 1, pose={"x": 0.0, "y": 0.0, "yaw": 0.0})
    state = stream_state(client, "car")
    for changes in ({"image": detect_json("car", 0.25, frame(9))["image"]}, {"pose": {"x": 1.0, "y": 0.0, "yaw": 0.0}}):
        body = {**detect_json("car", PERIOD, frame(1), (0.0, 0.0, 0.0)), **changes}
        response = client.post("/detect", json=body)
        assert response.status_code == 409, response.text
        assert response.json()["error"]["code"] == "timestamp_not_increasing"
        assert "another image or pose" in response.json()["error"]["message"]
    assert stream_state(client, "car") == state


def test_an_older_frame_than_the_last_is_still_refused(app_parts):
    client, _, _ = app_parts
    post(client, 1)
    post(client, 2)
    response = client.post("/detect", json=detect_json("car", PERIOD, frame(1)))
    assert response.status_code == 409 and "not after" in response.json()["error"]["message"]


def test_a_replica_that_never_saw_the_frame_takes_it_as_new(app_parts):
    """The retry reaches a replica without the stream (failover): a new chain, not a replay, not an error."""
    client, _, _ = app_parts
    fresh = post(client, 5, previous=4, stream="moved")
    assert fresh["frames_used"] == 1 and "replayed" not in fresh and "stream_restarted" not in fresh
