"""Timestamps, gaps and poses within physical ranges (issue 40, findings 4 and 5): a timestamp outside 0 to 2100, a
gap below RAFD_MIN_FRAME_GAP_S, a pose beyond 1e8 m or a yaw beyond 1e4 rad, and a pose that moved faster than
RAFD_MAX_SPEED_MPS are each refused with 422 naming the rule, and the stream keeps what it had (no silent zero
motion, no chain bent for good)."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from tests.utils.fake_runner import FakeRunner
from tests.utils.service_testing import FakeOdometry, blob_frame, detect_json, stream_state, wait_ready

FRAME = blob_frame(128, [(8, 8, 255)])


def refused(response, code: str, words: str) -> None:
    assert response.status_code == 422, response.text
    error = response.json()["error"]
    assert error["code"] == code and words in error["message"], error


@pytest.mark.parametrize(
    "timestamp, words",
    [(-1.0, "greater than or equal to 0"), (-1e308, "greater than or equal to 0"), (1e308, "less than or equal to")],
)
def test_a_timestamp_outside_the_epoch_range_is_refused(client: TestClient, timestamp: float, words: str):
    refused(client.post("/detect", json=detect_json("t", timestamp, FRAME)), "validation_error", words)
    form = client.post(
        "/detect",
        data={"stream_id": "t", "timestamp": repr(timestamp)},
        files={"image": ("f.png", b"\x89PNG", "image/png")},
    )
    refused(form, "validation_error", words)
    assert stream_state(client, "t") is None


def test_small_and_real_timestamps_are_accepted(client: TestClient):
    """Small test timestamps (the README's curl posts 1, 2) and real UNIX times both pass."""
    for stream, times in (("small", (0.0, 1.0, 2.0)), ("unix", (1574859771.74, 1574859771.99))):
        for t in times:
            assert client.post("/detect", json=detect_json(stream, t, FRAME)).status_code == 200


@pytest.mark.parametrize("gap", [5e-324, 1e-300, 1e-3])
def test_a_gap_below_the_minimum_is_refused_and_leaves_the_stream(client: TestClient, gap: float):
    """The finding: gaps of 5e-324 s or 1e-300 s answered 200 with zero motion."""
    assert client.post("/detect", json=detect_json("g", 0.0, FRAME)).status_code == 200  # 0 + 5e-324 is not 0
    before = stream_state(client, "g")
    refused(client.post("/detect", json=detect_json("g", gap, FRAME)), "timestamp_gap_too_small", "min_frame_gap")
    assert stream_state(client, "g") == before
    answer = client.post("/detect", json=detect_json("g", 0.25, FRAME))
    assert answer.status_code == 200 and answer.json()["frames_used"] == 2


@pytest.mark.parametrize(
    "pose, words",
    [
        ((1e9, 0.0, 0.0), "less than or equal to 100000000"),
        ((0.0, -1e300, 0.0), "greater than or equal to -100000000"),
        ((0.0, 0.0, 1e300), "less than or equal to 10000"),
    ],
)
def test_a_pose_outside_the_physical_range_is_refused(client: TestClient, pose, words: str):
    refused(client.post("/detect", json=detect_json("p", 1.0, FRAME, pose)), "validation_error", words)


def test_a_pose_faster_than_a_road_vehicle_is_refused_and_the_chain_keeps_its_pose(client: TestClient):
    """100 m in 0.25 s (400 m/s) is refused with the rule named; the next plausible frame continues the chain from
    the last accepted pose, so nothing is offset afterwards."""
    assert client.post("/detect", json=detect_json("v", 1.0, FRAME, (0.0, 0.0, 0.0))).status_code == 200
    before = stream_state(client, "v")
    jump = client.post("/detect", json=detect_json("v", 1.25, FRAME, (0.0, 100.0, 0.0)))
    refused(jump, "implausible_motion", "rule max_speed")
    assert "70 m/s" in jump.json()["error"]["message"]
    assert stream_state(client, "v") == before
    fast_road = client.post("/detect", json=detect_json("v", 1.5, FRAME, (0.0, 15.0, 0.0)))  # 30 m/s: a motorway
    assert fast_road.status_code == 200 and fast_road.json()["pose"]["y"] == 15.0
    assert fast_road.json()["frames_used"] == 2


def test_odometry_faster_than_a_road_vehicle_is_refused(settings):
    """Without poses, an odometry step of 2 m in 0.02 s (100 m/s) is refused the same way, and the stream's pose
    stays where it was; at 0.25 s the same step (8 m/s) passes."""
    with TestClient(create_app(settings, runner=FakeRunner(), odometry=FakeOdometry((0.0, 2.0, 0.0)))) as client:
        wait_ready(client)
        assert client.post("/detect", json=detect_json("o", 1.0, FRAME)).status_code == 200
        refused(client.post("/detect", json=detect_json("o", 1.02, FRAME)), "implausible_motion", "rule max_speed")
        answer = client.post("/detect", json=detect_json("o", 1.25, FRAME))
        assert answer.status_code == 200 and answer.json()["pose"]["y"] == pytest.approx(2.0)


def test_the_speed_rule_is_a_setting(settings):
    """RAFD_MAX_SPEED_MPS=0 turns the rule off (e.g. for a replayed log whose poses jump)."""
    off = settings.model_copy(update={"max_speed_mps": 0.0})
    with TestClient(create_app(off, runner=FakeRunner(), odometry=FakeOdometry())) as client:
        wait_ready(client)
        assert client.post("/detect", json=detect_json("v", 1.0, FRAME, (0.0, 0.0, 0.0))).status_code == 200
        assert client.post("/detect", json=detect_json("v", 1.25, FRAME, (0.0, 100.0, 0.0))).status_code == 200
