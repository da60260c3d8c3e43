"""rafd.tracking.tracker: ids, life cycle, ego motion removed, NaN inputs, bounded state, an immutable state."""

from __future__ import annotations

import numpy as np
import pytest

from rafd.tracking import (
    STATUS_NAMES,
    VELOCITY_SOURCES,
    FlowField,
    FlowGrid,
    FrameRefused,
    TrackerSettings,
    TrackerState,
    step,
)

PERIOD = 0.25  # seconds between scans (4 Hz)


def ego_pose(k: int) -> np.ndarray:
    """The ego drives 2 m per scan along a heading of 0.3 rad, far from the world's origin (UTM-sized numbers)."""
    return np.array([6.0e5 + 2.0 * k * np.cos(0.3), 5.7e6 + 2.0 * k * np.sin(0.3), 0.3])


def to_ego(pose: np.ndarray, world_xy: np.ndarray) -> np.ndarray:
    cos, sin = np.cos(pose[2]), np.sin(pose[2])
    d = np.asarray(world_xy, np.float64) - pose[:2]
    return np.stack([cos * d[..., 0] + sin * d[..., 1], -sin * d[..., 0] + cos * d[..., 1]], -1)


def car(ego_xy: np.ndarray, yaw: float = 0.0) -> np.ndarray:
    return np.array([[ego_xy[0], ego_xy[1], 1.8, 4.5, yaw]])


def straight_line(frames: int, velocity=(10.0, 0.0), start=(6.0e5 + 10.0, 5.7e6 + 20.0)) -> list[np.ndarray]:
    """[frames] world centres of a car moving at a constant world velocity."""
    return [np.asarray(start) + PERIOD * k * np.asarray(velocity) for k in range(frames)]


def run(frames, settings=TrackerSettings(), state=None, flows=None):
    state = TrackerState.empty() if state is None else state
    answers = []
    for k, boxes in enumerate(frames):
        flow = None if flows is None else flows[k]
        answer, state = step(state, boxes, ego_pose(k), 100.0 + PERIOD * k, flow=flow, settings=settings)
        answers.append(answer)
    return answers, state


def test_a_straight_line_target_keeps_one_id_and_its_ground_velocity():
    centres = straight_line(8)
    answers, state = run([car(to_ego(ego_pose(k), c)) for k, c in enumerate(centres)], TrackerSettings("filter"))
    assert [a.track_id.tolist() for a in answers] == [[1]] * 8
    assert [STATUS_NAMES[a.status[0]] for a in answers[:3]] == ["tentative", "confirmed", "confirmed"]
    assert [VELOCITY_SOURCES[a.velocity_source[0]] for a in answers[:2]] == ["none", "track"]
    assert answers[0].age.tolist() == [1] and answers[-1].age.tolist() == [8] and answers[-1].hits.tolist() == [8]
    # 10 m/s east in the world, seen from an ego heading 0.3 rad: the ego's own 8 m/s is removed
    truth = to_ego(np.array([0.0, 0.0, 0.3]), np.array([10.0, 0.0]))
    assert np.allclose(answers[-1].velocity[0], truth, atol=0.05)
    std = np.sqrt(np.diagonal(answers[-1].velocity_covariance[0]))
    assert np.all(std < 2.0) and np.all(std > 0)
    assert state.next_id == 2


def test_two_crossing_targets_keep_their_ids():
    a = straight_line(10, velocity=(8.0, 4.0), start=(6.0e5, 5.7e6 + 10.0))
    b = straight_line(10, velocity=(8.0, -4.0), start=(6.0e5, 5.7e6 + 30.0))
    frames = [np.concatenate([car(to_ego(ego_pose(k), a[k])), car(to_ego(ego_pose(k), b[k]))]) for k in range(10)]
    answers, _ = run(frames, TrackerSettings("filter"))
    assert all(answer.track_id.tolist() == [1, 2] for answer in answers)


def test_ids_are_never_reused_after_a_track_ends():
    centre = straight_line(1)[0]
    frames = [car(to_ego(ego_pose(0), centre)), np.zeros((0, 5)), car(to_ego(ego_pose(2), centre))]
    ending = TrackerSettings(tentative_coast_frames=0)
    answers, state = run(frames, ending)  # tentative, missed (ends), a new detection at the same place
    assert answers[0].track_id.tolist() == [1] and len(answers[1]) == 0 and answers[2].track_id.tolist() == [2]
    assert state.next_id == 3
    kept, _ = run(frames, TrackerSettings(tentative_coast_frames=1))  # a tentative track outlives one miss
    assert kept[2].track_id.tolist() == [1]
    _, restarted = run([car([0.0, 10.0])], state=TrackerState.empty(first_id=100))
    assert restarted.ids.tolist() == [100]


def test_a_confirmed_track_coasts_then_ends():
    centres = straight_line(9)
    seen = {0, 1, 2, 6}  # missed for 3 scans (coasts), seen again: same id
    frames = [car(to_ego(ego_pose(k), c)) if k in seen else np.zeros((0, 5)) for k, c in enumerate(centres[:7])]
    coasting = TrackerSettings("filter", answer_coasting=True, max_coast_frames=3)
    answers, state = run(frames, coasting)
    assert [a.track_id.tolist() for a in answers] == [[1]] * 7
    assert [STATUS_NAMES[a.status[0]] for a in answers] == ["tentative"] + ["confirmed"] * 2 + ["coasting"] * 3 + [
        "confirmed"
    ]
    assert answers[3].detection_index.tolist() == [-1] and answers[6].detection_index.tolist() == [0]
    assert answers[5].scores[0] == pytest.approx(0.7**3)  # decayed per missed scan
    # a coasting box is where the track predicts it (3 detections in: its velocity is not settled yet)
    assert np.allclose(answers[5].boxes[0, :2], to_ego(ego_pose(5), centres[5]), atol=0.5)
    # one scan more missed than max_coast_frames: it ends; hidden coasting answers nothing
    gone, _ = run(frames[:3] + [np.zeros((0, 5))] * 4, coasting)
    assert [len(a) for a in gone] == [1, 1, 1, 1, 1, 1, 0]
    hidden, _ = run(frames[:4], TrackerSettings("filter"))
    assert len(hidden[3]) == 0
    assert len(state) == 1


def test_tentative_tracks_can_be_withheld():
    answers, _ = run([car([0.0, 10.0]), car([0.0, 10.0])], TrackerSettings(answer_tentative=False))
    assert len(answers[0]) == 0 and answers[1].track_id.tolist() == [1]


def test_non_finite_boxes_are_dropped_with_a_reason_and_never_reach_a_track():
    boxes = np.array(
        [
            [0.0, 10.0, 1.8, 4.5, 0.0],
            [np.nan, 10.0, 1.8, 4.5, 0.0],
            [5.0, np.inf, 1.8, 4.5, 0.0],
            [5.0, 5.0, 0.0, 4.5, 0.0],
            [5.0, 5.0, 1.8, 4.5, np.nan],
            [1e9, 5.0, 1.8, 4.5, 0.0],
        ]
    )
    scores = np.array([0.9, 0.9, 0.9, 0.9, 0.9, 0.9])
    answer, state = step(TrackerState.empty(), boxes, ego_pose(0), 100.0, scores=scores)
    assert answer.detection_index.tolist() == [0]
    assert dict(answer.dropped) == {
        1: "non-finite box",
        2: "non-finite box",
        3: "non-positive size",
        4: "non-finite box",
        5: "farther than 10000 m",
    }
    answer, state = step(state, boxes[:1], ego_pose(1), 100.25, scores=np.array([np.nan]))
    assert dict(answer.dropped) == {0: "non-finite score"} and len(answer) == 0
    assert np.isfinite(state.mean).all() and np.isfinite(state.covariance).all()


@pytest.mark.parametrize(
    ("pose", "timestamp"),
    [([np.nan, 0.0, 0.0], 101.0), ([0.0, 0.0, np.inf], 101.0), ([0.0, 0.0], 101.0), (np.zeros(3), np.nan)],
)
def test_a_non_finite_pose_or_time_refuses_the_frame_and_leaves_the_state(pose, timestamp):
    _, state = step(TrackerState.empty(), car([0.0, 10.0]), np.zeros(3), 100.0)
    with pytest.raises(FrameRefused):
        step(state, car([0.0, 10.0]), pose, timestamp)
    assert state.timestamp == 100.0 and state.ids.tolist() == [1]


def test_a_replayed_frame_is_refused_and_an_old_state_steps_again_to_the_same_answer():
    centres = straight_line(4)
    frames = [car(to_ego(ego_pose(k), c)) for k, c in enumerate(centres)]
    _, state = run(frames[:2])
    first, after = step(state, frames[2], ego_pose(2), 100.5)
    with pytest.raises(FrameRefused, match="not after"):
        step(after, frames[2], ego_pose(2), 100.5)  # the same frame again
    again, after_again = step(state, frames[2], ego_pose(2), 100.5)  # the old state is still valid
    for name in ("track_id", "boxes", "velocity", "velocity_covariance", "status", "age", "hits"):
        assert np.array_equal(getattr(first, name), getattr(again, name))
    assert np.array_equal(after.mean, after_again.mean) and after.next_id == after_again.next_id
    assert state.timestamp == 100.25 and state.hits.tolist() == [2]
    with pytest.raises(ValueError):
        state.mean[0, 0] = 1.0  # read-only


def test_live_tracks_are_bounded():
    settings = TrackerSettings("filter", max_tracks=4, answer_coasting=True)
    many = np.array([[x, 10.0, 1.8, 4.5, 0.0] for x in range(0, 60, 10)])
    answer, state = step(TrackerState.empty(), many, np.zeros(3), 0.0, scores=np.arange(6.0), settings=settings)
    assert len(state) == 4 and sorted(answer.detection_index.tolist()) == [2, 3, 4, 5]
    assert dict(answer.dropped) == {0: "track cap", 1: "track cap"}
    for k in range(1, 3):  # confirm them, then a new crowd elsewhere evicts the coasting ones
        _, state = step(state, many[2:], np.zeros(3), 0.25 * k, scores=np.arange(4.0), settings=settings)
    crowd = many[2:].copy()
    crowd[:, 1] = -30.0
    answer, state = step(state, crowd[:3], np.zeros(3), 0.75, scores=np.ones(3), settings=settings)
    assert len(state) == 4 and (answer.detection_index >= 0).sum() == 3 and (answer.detection_index < 0).sum() == 1


def test_a_long_gap_ends_every_track():
    _, state = run([car([0.0, 10.0])] * 2)
    answer, state = step(state, car([0.0, 10.0]), ego_pose(2), 100.25 + 5.0)
    assert answer.track_id.tolist() == [2]


def test_the_flow_seeds_a_new_tracks_velocity():
    grid = FlowGrid.centred(64, 64, 0.694)
    truth = np.array([3.0, -2.0])  # m/s in the ego axes
    flow = np.zeros((2, 64, 64))
    flow[:, 20:44, 20:44] = (truth * PERIOD)[:, None, None]
    field = FlowField(grid, flow, PERIOD, np.ones((64, 64)), reach_m=4.2)
    seeded = TrackerSettings("filter_flow")
    answer, _ = step(TrackerState.empty(), car([0.0, 0.0]), np.array([5.0, 5.0, 1.0]), 0.0, flow=field, settings=seeded)
    assert VELOCITY_SOURCES[answer.velocity_source[0]] == "flow"
    assert np.allclose(answer.velocity[0], truth)
    assert np.allclose(answer.velocity_covariance[0], 0.25 * np.eye(2))  # the floor alone: a uniform flow
    without, _ = step(TrackerState.empty(), car([0.0, 0.0]), np.zeros(3), 0.0, flow=field)  # the default: filter
    assert VELOCITY_SOURCES[without.velocity_source[0]] == "none" and np.allclose(without.velocity[0], 0.0)
    centre_only, _ = step(
        TrackerState.empty(), car([0.0, 0.0]), np.zeros(3), 0.0, flow=field, settings=TrackerSettings("flow_centre")
    )
    assert np.allclose(centre_only.velocity[0], truth)
