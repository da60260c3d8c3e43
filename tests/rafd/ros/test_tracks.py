"""An answered box's identity and motion for RadarTracks / Detection3D, with and without the service's tracking
fields (synthetic answers carrying the planned fields)."""

from __future__ import annotations

import math
import uuid

import numpy as np

from rafd.ros.tracks import TRACK_NAMESPACE, track_fields, upper_triangle_3d

TRACKED = {
    "x": 2.0,
    "y": 30.0,
    "track_id": "17",
    "velocity": {"x": 1.0, "y": 8.0},
    "velocity_covariance": [[0.25, 0.05], [0.05, 1.0]],
    "velocity_source": "track",
    "track": {"status": "confirmed", "age": 12, "hits": 10},
}


def test_a_tracked_box_keeps_its_uuid_and_turns_its_velocity():
    first = track_fields(TRACKED, "car-1", 1_000, 0)
    later = track_fields(TRACKED, "car-1", 2_000, 5)  # another scan, another place in the answer
    assert first.uuid == later.uuid == uuid.uuid5(TRACK_NAMESPACE, "car-1/track/17").bytes
    assert first.id == "17" and first.tracked and first.status == "confirmed" and first.velocity_source == "track"
    assert first.velocity == (8.0, -1.0)  # forward 8 m/s, 1 m/s to the right
    np.testing.assert_allclose(first.velocity_covariance, [[1.0, -0.05], [-0.05, 0.25]])
    assert track_fields(TRACKED, "car-2", 1_000, 0).uuid != first.uuid  # unique within a stream, not across


def test_an_untracked_box_gets_a_uuid_of_its_own_and_nan_motion():
    box = {"x": 2.0, "y": 30.0}  # today's answers
    a, b = track_fields(box, "car-1", 1_000, 0), track_fields(box, "car-1", 1_000, 1)
    c = track_fields(box, "car-1", 2_000, 0)
    assert len({a.uuid, b.uuid, c.uuid}) == 3 and not a.tracked and a.status is None
    assert a.id == "car-1/scan/1000/box/0"
    assert all(math.isnan(v) for v in a.velocity) and np.isnan(a.velocity_covariance).all()
    assert a.velocity_source == "none"


def test_a_null_velocity_or_covariance_is_unknown():
    no_velocity = dict(TRACKED, velocity=None, velocity_source="none")
    fields = track_fields(no_velocity, "s", 0, 0)
    assert fields.tracked and all(math.isnan(v) for v in fields.velocity) and fields.velocity_source == "none"
    no_covariance = dict(TRACKED, velocity_covariance=None)
    fields = track_fields(no_covariance, "s", 0, 0)
    assert fields.velocity == (8.0, -1.0) and np.isnan(fields.velocity_covariance).all()
    broken = dict(TRACKED, velocity={"x": "fast", "y": 1.0})
    assert all(math.isnan(v) for v in track_fields(broken, "s", 0, 0).velocity)


def test_the_upper_triangle_leaves_height_unknown():
    values = upper_triangle_3d(np.array([[1.0, 0.5], [0.5, 2.0]]))
    assert values[:2] == [1.0, 0.5] and values[3] == 2.0 and all(math.isnan(values[i]) for i in (2, 4, 5))
