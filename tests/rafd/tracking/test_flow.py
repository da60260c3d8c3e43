"""rafd.tracking.flow: the grid rule, velocity from a known synthetic flow (centre and box), validity, saturation,
non-finite cells, mosaics."""

from __future__ import annotations

import numpy as np
import pytest

from rafd.geometry import feature_cell_centres, points_in_boxes
from rafd.tracking.flow import FlowField, FlowGrid, flow_velocity, sample_box, sample_centre

CELL = 0.694


def test_a_centred_grid_is_the_models_cell_rule():
    grid = FlowGrid.centred(64, 64, 256 * 0.173611 / 64)
    assert np.allclose(grid.centres(), feature_cell_centres(64, 256, 0.173611))
    shifted = FlowGrid.centred(64, 64, grid.cell_size_m, offset_m=(38.9, -38.9))
    assert np.allclose(shifted.centres(), grid.centres() + np.array([38.9, -38.9]), atol=1e-3)
    assert np.allclose(grid.cells_of(grid.centres()[5, 7][None]), [[5, 7]])


def linear_field(grid: FlowGrid) -> np.ndarray:
    """flow = (0.1 x + 0.2, -0.05 y + 0.3) metres: bilinear sampling reproduces it exactly inside the grid."""
    centres = grid.centres()
    return np.stack([0.1 * centres[..., 0] + 0.2, -0.05 * centres[..., 1] + 0.3])


def test_the_centre_sample_is_bilinear():
    grid = FlowGrid.centred(32, 32, CELL)
    field = FlowField(grid, linear_field(grid), 0.25)
    points = np.array([[0.1, 0.2], [-3.3, 5.05], [7.77, -2.2]])
    flow, validity = sample_centre(field, points)
    assert np.allclose(flow, np.stack([0.1 * points[:, 0] + 0.2, -0.05 * points[:, 1] + 0.3], -1))
    assert np.allclose(validity, 1.0)
    off, off_validity = sample_centre(field, np.array([[100.0, 0.0]]))
    assert off_validity[0] == 0.0 and np.all(off == 0.0)


def test_the_box_sample_weights_exactly_the_cells_inside_the_box():
    rng = np.random.default_rng(0)
    grid = FlowGrid.centred(40, 40, CELL)
    flow = rng.normal(0.0, 1.0, (2, 40, 40))
    validity = rng.uniform(0.0, 1.0, (40, 40))
    field = FlowField(grid, flow, 0.25, validity)
    boxes = np.array([[1.0, 2.0, 1.8, 4.5, 0.4], [-5.0, 3.3, 2.5, 12.0, -1.2], [12.9, -12.9, 1.8, 4.5, 2.0]])
    mean, spread, mean_validity, cells = sample_box(field, boxes)
    inside = points_in_boxes(grid.centres().reshape(-1, 2), boxes)  # [H*W, N] brute force
    for k in range(len(boxes)):
        w = validity.reshape(-1)[inside[:, k]]
        f = flow.reshape(2, -1)[:, inside[:, k]]
        expected = (f * w).sum(1) / w.sum()
        assert cells[k] == inside[:, k].sum()
        assert np.allclose(mean[k], expected)
        assert mean_validity[k] == pytest.approx(w.mean())
        variance = ((f - expected[:, None]) ** 2 * w).sum() / (2 * w.sum())
        assert spread[k] == pytest.approx(np.sqrt(variance))


def test_velocity_from_a_known_synthetic_flow():
    grid = FlowGrid.centred(64, 64, CELL)
    truth = np.array([[4.0, -1.0], [-2.0, 6.0]])  # m/s, two cars
    boxes = np.array([[-8.0, 5.0, 1.8, 4.5, 0.2], [9.0, -6.0, 1.8, 4.5, 1.3]])
    interval = 0.24
    flow = np.zeros((2, 64, 64))
    inside = points_in_boxes(grid.centres().reshape(-1, 2), boxes).reshape(64, 64, 2)
    for k in range(2):
        flow[:, inside[..., k]] = (truth[k] * interval)[:, None]
    field = FlowField(grid, flow, interval, reach_m=4.2)
    for how in ("box", "centre"):
        measured = flow_velocity(field, boxes, how, std_floor=0.5, min_validity=0.5, reach_fraction=0.9)
        assert np.allclose(measured.velocity, truth, atol=1e-9)
        assert np.allclose(measured.variance, 0.25) and not measured.saturated.any()


def test_saturated_invalid_and_non_finite_flow_gives_no_velocity():
    grid = FlowGrid.centred(32, 32, CELL)
    box = np.array([[0.0, 0.0, 1.8, 4.5, 0.0]])
    fast = FlowField(grid, np.full((2, 32, 32), 3.0), 0.25, reach_m=4.2)  # |flow| 4.24 m: at the search's edge
    assert flow_velocity(fast, box, "box", 0.5, 0.5, 0.9).saturated[0]
    assert np.isnan(flow_velocity(fast, box, "box", 0.5, 0.5, 0.9).velocity).all()
    unseen = FlowField(grid, np.zeros((2, 32, 32)), 0.25, validity=np.full((32, 32), 0.2))
    assert np.isnan(flow_velocity(unseen, box, "box", 0.5, 0.5, 0.9).velocity).all()
    poisoned = np.zeros((2, 32, 32))
    poisoned[:, 15, 15:17] = np.nan  # two cells in the middle of the box
    measured = flow_velocity(FlowField(grid, poisoned, 0.25), box, "box", 0.5, 0.5, 0.9)
    assert np.isfinite(measured.velocity).all() and np.allclose(measured.velocity, 0.0)
    assert measured.validity[0] < 1.0
    all_nan = FlowField(grid, np.full((2, 32, 32), np.nan), 0.25)
    assert np.isnan(flow_velocity(all_nan, box, "box", 0.5, 0.5, 0.9).velocity).all()
    bad_interval = FlowField(grid, np.zeros((2, 32, 32)), 0.0)
    assert np.isnan(flow_velocity(bad_interval, box, "centre", 0.5, 0.5, 0.9).velocity).all()


def test_a_mosaic_box_reads_the_tile_that_measured_it_best():
    left = FlowGrid.centred(32, 32, CELL, offset_m=(-10.0, 0.0))
    right = FlowGrid.centred(32, 32, CELL, offset_m=(10.0, 0.0))
    weak = FlowField(left, np.full((2, 32, 32), 0.5), 0.25, validity=np.full((32, 32), 0.6))
    strong = FlowField(right, np.full((2, 32, 32), 0.25), 0.25)
    boxes = np.array([[0.0, 0.0, 1.8, 4.5, 0.0], [-20.0, 0.0, 1.8, 4.5, 0.0], [60.0, 0.0, 1.8, 4.5, 0.0]])
    measured = flow_velocity([weak, strong], boxes, "box", 0.5, 0.5, 0.9)
    assert np.allclose(measured.velocity[0], 1.0) and np.allclose(measured.velocity[1], 2.0)
    assert np.isnan(measured.velocity[2]).all()  # on no tile
