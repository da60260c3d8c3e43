"""rafd.runtime.view: tile geometry, tile frames' poses, what a view covers, merging, the mosaic of maps, and a whole
scan stepped through a runner."""

from __future__ import annotations

import numpy as np
import pytest

from rafd.geometry import invert_pose, pixels_to_metres, relative_pose, transform_points
from rafd.protocol import OperatingThreshold
from rafd.runtime.view import TileGrid, View, step_view, tile_poses

RES = 0.173611


def test_the_grid_covers_the_scan_symmetrically_with_overlap() -> None:
    grid = TileGrid.for_model(256)
    assert (grid.per_side, grid.stride) == (5, 224)
    offsets = grid.offsets_px
    assert offsets.min() == -448 and offsets.max() == 448 and len(offsets) == 25
    scan = np.arange(1152 * 1152, dtype=np.int64).reshape(1152, 1152) % 251
    crops = grid.crops(scan.astype(np.uint8))
    assert crops.shape == (25, 256, 256)
    np.testing.assert_array_equal(crops[12], scan[448:704, 448:704])  # the centre tile is the centre crop
    np.testing.assert_array_equal(crops[0], scan[:256, :256])  # top-left: the scan's corner (far left, ahead)
    assert TileGrid.for_model(128).stride <= 128 - 32
    assert TileGrid.for_model(256, 576, step=4).stride % 4 == 0
    with pytest.raises(ValueError, match="cover"):
        TileGrid(1152, 256, 200)


def test_tile_offsets_in_metres_and_ownership_agree_with_the_pixels() -> None:
    grid = TileGrid.for_model(256)
    centres_m = pixels_to_metres(grid.offsets_px + 576, 1152)
    np.testing.assert_allclose(grid.offsets_m, centres_m, atol=1e-9)
    assert grid.owner(grid.offsets_m).tolist() == list(range(25))
    assert grid.owner(np.array([[0.0, 0.0], [80.0, 80.0], [-500.0, 0.0]])).tolist() == [12, 4, 10]


def test_tile_frames_move_like_rigid_shifts_of_the_ego_frame() -> None:
    """A static world point seen in two scans: in each tile's frame it sits where the tiles' relative pose says."""
    grid = TileGrid.for_model(256)
    poses = np.array([[10.0, 5.0, 0.3], [12.0, 7.5, 0.45]])
    tiles = tile_poses(poses, grid.offsets_m)  # [25, 2, 3]
    point = np.array([30.0, 40.0])  # world
    ego = [transform_points(invert_pose(pose), point) for pose in poses]  # where each scan sees it
    for index in (0, 7, 12, 24):
        in_tile = [seen - grid.offsets_m[index] for seen in ego]
        moved = transform_points(relative_pose(tiles[index, 0], tiles[index, 1]), in_tile[0])
        np.testing.assert_allclose(moved, in_tile[1], atol=1e-9)


def test_a_view_covers_the_scan_the_range_asks_for() -> None:
    whole = View.of(1152, 256, RES, 4)
    assert whole.side_px == 1152 and whole.origin_px == 0 and whole.range_m is None
    assert len(whole.tiles) == 21 and not {0, 4, 20, 24} & set(whole.tiles)  # the corners lie outside the circle
    near = View.of(1152, 256, RES, 4, range_m=50.0)
    assert (near.side_px, near.grid.stride, near.origin_px) == (584, 164, 284) and len(near.tiles) == 9
    assert near.range_m == 50.0 and near.side_px * RES >= 100.0
    for range_m, tiles in ((30.0, 4), (60.0, 9), (75.0, 12), (99.0, 21)):  # the fewest tiles holding the disc
        assert len(View.of(1152, 256, RES, 4, range_m=range_m).tiles) == tiles, range_m
    with pytest.raises(ValueError, match="no grid"):
        TileGrid.for_model(256, 578, step=4)
    crop = View.of(1152, 256, RES, 4, range_m=10.0)  # the model's size is the least a view covers
    assert (crop.side_px, crop.tiles, crop.origin_px) == (256, (0,), 448)
    posted_crop = View.of(256, 256, RES, 4)  # a crop posted: one tile, as today
    assert (posted_crop.side_px, posted_crop.tiles) == (256, (0,))
    np.testing.assert_allclose(whole.tile_poses(np.zeros(3))[:, :2], whole.grid.offsets_m[list(whole.tiles)])


def test_a_vehicle_on_a_tile_border_is_reported_once_where_it_is_and_none_beyond_the_range() -> None:
    view = View.of(1152, 256, RES, 4, range_m=100.0)
    grid, tiles = view.grid, view.tiles
    border_x = grid.stride * grid.resolution / 2.0 + 0.8  # just inside tile 13's core (right of the centre tile)
    boxes = np.zeros((len(tiles), 4, 5))
    scores = np.zeros((len(tiles), 4))
    for tile in (12, 13):  # both tiles see it, each in its own frame
        row = tiles.index(tile)
        boxes[row, 0] = [border_x - grid.offsets_m[tile, 0], 3.0 - grid.offsets_m[tile, 1], 1.9, 4.6, 0.1]
        scores[row, 0] = 0.8 if tile == 12 else 0.7
    far = tiles.index(2)  # the tile straight ahead at the edge: a box 99.5 m ahead, and one beyond the range
    boxes[far, 0] = [0.0, 99.5 - grid.offsets_m[2, 1], 1.9, 4.6, 0.0]
    boxes[far, 1] = [15.0, 99.5 - grid.offsets_m[2, 1], 1.9, 4.6, 0.0]  # 100.6 m from the radar
    scores[far, :2] = 0.9
    boxes[:, :, 2:4] = np.maximum(boxes[:, :, 2:4], 1.0)
    merged = view.merge(boxes, scores, score_threshold=0.3)
    assert len(merged) == 2
    np.testing.assert_allclose(merged.boxes[:, :2], [[0.0, 99.5], [border_x, 3.0]], atol=1e-9)
    assert merged.scores[1] == pytest.approx(0.7)  # tile 13 owns it, whatever tile 12 scored
    # a far threshold from 50 m: the 99.5 m box (0.9) needs 0.95, the 3 m one keeps the near 0.3
    far = view.merge(boxes, scores, score_threshold=OperatingThreshold(0.3, far=0.95, far_from_m=50.0))
    np.testing.assert_allclose(far.boxes[:, :2], [[border_x, 3.0]], atol=1e-9)
    # the border vehicle's owner scores 0.5 < 0.6 (near): not answered, and tile 12's 0.8 copy is not its to answer
    scores[tiles.index(13), 0] = 0.5
    far_only = view.merge(boxes, scores, score_threshold=OperatingThreshold(0.6, far=0.3, far_from_m=90.0))
    assert len(far_only) == 1 and far_only.scores[0] == pytest.approx(0.9)


def test_the_mosaic_takes_each_cell_from_the_tile_whose_core_holds_it() -> None:
    view = View.of(1152, 256, RES, 4, range_m=50.0)  # 3 x 3 tiles over 584 px, stride 164 px = 41 cells
    views, cells = len(view.tiles), 256 // 4
    rows, columns = np.meshgrid(np.arange(cells), np.arange(cells), indexing="ij")
    maps = np.stack([np.stack([np.full((cells, cells), t), rows * 100 + columns]) for t in range(views)])
    mosaic = view.mosaic(maps.astype(np.float32))  # [2, 146, 146]
    assert mosaic.shape == (2, 146, 146)
    assert mosaic[0, 73, 73] == view.tiles.index(4) and mosaic[0, 0, 0] == view.tiles.index(0)
    # the centre cell of the covered square is the centre tile's cell (32, 32); a cell 41 cells right is tile 5's
    assert mosaic[1, 73, 73] == 32 * 100 + 32 and mosaic[0, 73, 114] == view.tiles.index(5)
    assert mosaic[1, 73, 114] == 32 * 100 + 32
    whole = View.of(1152, 256, RES, 4)  # cells of the skipped corner tiles are 0
    corner = whole.mosaic(np.ones((len(whole.tiles), 64, 64), np.float32))
    assert corner[0, 0] == 0 and corner[144, 144] == 1


@pytest.mark.slow
def test_a_full_scan_steps_through_the_shipped_runner_as_one_batch() -> None:
    from rafd.assets import default_onnx
    from rafd.runtime import OnnxRunner
    from rafd.sim import Difficulty
    from rafd.sim.sequence import run_simulation

    runner = OnnxRunner(default_onnx(), threads=1)
    calls = []
    run = runner.run
    runner.run = lambda feeds: calls.append(len(feeds["frame"])) or run(feeds)  # type: ignore[method-assign]
    view = View.of(1152, runner.config.input_size, runner.config.resolution, 4)
    sequence = run_simulation(5, 2, "test", 1152, Difficulty(), name="tiles")
    state = runner.new_state()
    for scan, pose in zip(sequence.images, sequence.poses):
        result, state = step_view(runner, state, view, scan, pose)
        found = view.merge(result.boxes, result.scores, score_threshold=0.3)
        assert np.all(np.isfinite(found.boxes)) and np.all(np.hypot(*found.boxes[:, :2].T) <= 100.1)
    assert state.frames_used == 2 and state.views == len(view.tiles) and calls == [21, 21]
