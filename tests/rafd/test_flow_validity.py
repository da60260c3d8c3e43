"""rafd.flow_validity: where the flow was measured over the whole search range, from geometry alone."""

from __future__ import annotations

import numpy as np
import pytest

from rafd.flow_validity import FLOW_VALID_MIN, flow_validity, search_reach_m
from rafd.geometry import relative_pose

SIZE, INPUT, RES, STRIDE = 16, 64, 1.0, 4  # 16 x 16 cells of 4 m, matching on the detection grid itself


def validity(pose, local_radius: int = 0) -> np.ndarray:
    reach = search_reach_m(STRIDE, RES, local_radius)
    return flow_validity(np.asarray(pose, np.float64), SIZE, INPUT, RES, STRIDE, reach)


def test_search_reach_is_one_matching_cell_for_global_matching_and_the_radius_else():
    assert search_reach_m(4, 1.0, 0) == 4.0
    assert search_reach_m(8, 0.5, 3) == 12.0


def test_identity_pose_invalidates_the_outer_ring_only():
    valid = validity(np.zeros(3))
    assert valid.shape == (SIZE, SIZE) and valid.dtype == np.float32
    ring0 = np.ones((SIZE, SIZE), bool)
    ring0[1:-1, 1:-1] = False
    assert np.all(valid[ring0] == 0.0)  # the outermost matching ring measures no motion at all
    assert np.all(valid[1:-1, 1:-1] == 1.0) and np.all(valid[1:-1, 1:-1] >= FLOW_VALID_MIN)


def test_a_local_search_window_reaches_its_radius_in_from_the_edge():
    valid = validity(np.zeros(3), local_radius=2)  # reach 8 m = 2 cells
    assert valid[0, 8] == 0.0 and valid[1, 8] == pytest.approx(0.5) and valid[2, 8] == 1.0
    assert np.all(valid[2:-2, 2:-2] == 1.0)


def test_forward_ego_motion_invalidates_what_was_ahead_of_the_previous_crop():
    """One cell (4 m) forward: the row below the top edge held content beyond the previous crop's top edge."""
    moved = relative_pose(np.array([0.0, 0.0, 0.0]), np.array([0.0, 4.0, 0.0]))  # previous -> current ego
    np.testing.assert_allclose(moved, [0.0, -4.0, 0.0])
    valid = validity(moved)
    inner = slice(2, -2)
    assert np.all(valid[1, inner] == 0.0)  # ahead: was outside the previous crop
    assert np.all(valid[2, inner] == 1.0)
    assert np.all(valid[-2, inner] == 1.0)  # behind: seen before, only the outer ring stays invalid
    assert np.all(valid[-1, :] == 0.0)
    np.testing.assert_array_equal(valid[:, 1:-1], validity(moved)[:, 1:-1])  # pure geometry: repeatable


def test_validity_stays_in_zero_one_under_any_motion():
    rng = np.random.default_rng(0)
    for pose in rng.normal(0.0, [6.0, 6.0, 0.3], (20, 3)):
        valid = validity(pose, local_radius=1)
        assert valid.min() >= 0.0 and valid.max() <= 1.0
