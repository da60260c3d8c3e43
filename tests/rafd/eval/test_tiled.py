"""rafd.eval.tiled: tile geometry, tile frames' poses, border merging, and streaming a full scan through a runner."""

from __future__ import annotations

import numpy as np
import pytest

from rafd.eval.tiled import TiledStream, TileGrid, merge_tiles, tile_poses
from rafd.geometry import invert_pose, pixels_to_metres, relative_pose, transform_points


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


def test_a_vehicle_on_a_tile_border_is_reported_once_where_it_is() -> None:
    grid = TileGrid.for_model(256)
    border_x = grid.stride * grid.resolution / 2.0 + 0.8  # just inside tile 13's core (right of the centre tile)
    boxes = np.zeros((25, 4, 5))
    scores = np.zeros((25, 4))
    for tile in (12, 13):  # both tiles see it, each in its own frame
        boxes[tile, 0] = [border_x - grid.offsets_m[tile, 0], 3.0 - grid.offsets_m[tile, 1], 1.9, 4.6, 0.1]
        scores[tile, 0] = 0.8 if tile == 12 else 0.7
    boxes[:, :, 2:4] = np.maximum(boxes[:, :, 2:4], 1.0)
    merged = merge_tiles(grid, boxes, scores, score_threshold=0.3)
    assert len(merged) == 1
    np.testing.assert_allclose(merged.boxes[0, :2], [border_x, 3.0], atol=1e-9)
    assert merged.scores[0] == pytest.approx(0.7)  # tile 13 owns it, whatever tile 12 scored


@pytest.mark.slow
def test_a_full_scan_streams_through_the_shipped_runner(tmp_path) -> None:
    from rafd.assets import default_onnx
    from rafd.runtime import OnnxRunner
    from rafd.sim import Difficulty
    from rafd.sim.sequence import run_simulation

    runner = OnnxRunner(default_onnx(), threads=1)
    sequence = run_simulation(5, 2, "test", 1152, Difficulty(), name="tiles")
    stream = TiledStream(runner)
    for scan, pose in zip(sequence.images, sequence.poses):
        found = stream.step(scan, pose, score_threshold=0.3)
        assert np.all(np.isfinite(found.boxes)) and np.all(np.abs(found.boxes[:, :2]) < 101)
    assert stream.state.frames_used == 2 and stream.state.views == stream.grid.per_side**2
