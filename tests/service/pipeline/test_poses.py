"""The service's pose rule: odometry from the stream's tracker gives the same motion as the offline
OdometryStream, a frame's odometry never changes the memory it started from (a failed frame leaves the stream as it
was), and a custom pairwise odometry or a size switch registers the pair directly."""

from __future__ import annotations

import numpy as np
import pytest

from rafd.geometry import compose_poses
from rafd.odometry.registration import OdometryStream
from rafd.sim import Difficulty
from rafd.sim.sequence import run_simulation
from service.http.errors import ApiError
from service.pipeline.poses import check_request_pose, odometry_pose, remember

RES = 0.173611
STAMPS = [100.0 + 0.25 * k for k in range(4)]


@pytest.fixture(scope="module")
def scans() -> list[np.ndarray]:
    return run_simulation(44, 4, "test", 384, Difficulty(), name="poses").images


def test_the_service_chain_matches_the_offline_stream(scans):
    offline = OdometryStream(RES)
    expected = [np.zeros(3)]
    offline.add(scans[0], STAMPS[0])
    for image, stamp in zip(scans[1:], STAMPS[1:]):
        expected.append(compose_poses(expected[-1], offline.add(image, stamp)))

    pose, memory = np.zeros(3), remember(scans[0], STAMPS[0], None)
    for k in range(1, len(scans)):
        pose, memory = odometry_pose(pose, memory, scans[k], STAMPS[k], None, RES)
        np.testing.assert_allclose(pose, expected[k], atol=1e-9)
    assert memory.tracker is not None and memory.timestamp == STAMPS[-1]


def test_a_frame_leaves_the_memory_it_started_from_unchanged(scans):
    pose, memory = odometry_pose(np.zeros(3), remember(scans[0], STAMPS[0], None), scans[1], STAMPS[1], None, RES)
    tracker = memory.tracker
    assert tracker is not None
    before = (tracker.previous_time, None if tracker.prior is None else tracker.prior.copy(), tracker.period)
    first, after_first = odometry_pose(pose, memory, scans[2], STAMPS[2], None, RES)
    again, _ = odometry_pose(pose, memory, scans[2], STAMPS[2], None, RES)  # the same frame retried
    np.testing.assert_array_equal(first, again)
    assert (tracker.previous_time, tracker.period) == (before[0], before[2])
    np.testing.assert_array_equal(tracker.prior, before[1])
    assert after_first.tracker is not tracker


def test_a_custom_odometry_and_a_size_switch_register_the_pair(scans):
    calls = []

    def pairwise(previous, current, resolution):
        calls.append((previous.shape, current.shape))
        return np.array([0.0, 1.0, 0.0])

    pose, memory = odometry_pose(np.zeros(3), remember(scans[0], 0.0, None), scans[1], 0.25, None, RES, pairwise)
    np.testing.assert_allclose(pose, [0.0, 1.0, 0.0])
    assert calls == [((384, 384), (384, 384))] and memory.tracker is None

    crop = scans[2][64:320, 64:320]  # the stream switched to model-size crops: the full scan's centre is compared
    pose, memory = odometry_pose(pose, memory, crop, 0.5, None, RES, pairwise)
    assert calls[-1] == ((256, 256), (256, 256)) and memory.view.shape == (256, 256)


def test_a_bad_odometry_answer_and_a_pose_conflict_are_api_errors(scans):
    with pytest.raises(ApiError, match="3 finite numbers"):
        odometry_pose(
            np.zeros(3), remember(scans[0], 0.0, None), scans[1], 0.25, None, RES, lambda *_: np.array([np.nan] * 3)
        )
    with pytest.raises(ApiError, match="DELETE the stream"):
        check_request_pose("odometry")
    check_request_pose("request")
