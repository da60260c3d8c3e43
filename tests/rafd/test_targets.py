"""build_targets: CenterNet heatmap, regression targets with K padding, pseudo-GT flow with ego motion removed."""
from __future__ import annotations

import logging
import math

import numpy as np
import pytest

from rafd.config import HeadConfig, RaFDConfig
from rafd.geometry import feature_cell_centres
from rafd.targets import FLOW_MIN_RADIUS, build_targets, gaussian_radius

CFG = RaFDConfig.tiny(input_size=128)  # 32 x 32 cells of 0.694 m, K = 32


def _centernet_radius(h: float, w: float, o: float = 0.7) -> float:
    """CenterNet's gaussian_radius (CenterNet/src/lib/utils/image.py), transcribed."""
    r1 = ((h + w) + math.sqrt((h + w) ** 2 - 4 * w * h * (1 - o) / (1 + o))) / 2
    r2 = (2 * (h + w) + math.sqrt(4 * (h + w) ** 2 - 16 * (1 - o) * w * h)) / 2
    r3 = (-2 * o * (h + w) + math.sqrt(4 * o * o * (h + w) ** 2 + 16 * o * (1 - o) * w * h)) / 2
    return min(r1, r2, r3)


def _cell(x: float, y: float, cfg: RaFDConfig = CFG) -> tuple[int, int]:
    size = cfg.feature_size
    return int(math.floor(size / 2 - y / cfg.cell_size)), int(math.floor(x / cfg.cell_size + size / 2))


def test_gaussian_radius_matches_centernet() -> None:
    for h, w in [(6.5, 2.6), (17.0, 3.6), (10.0, 10.0), (1.0, 1.0)]:
        assert gaussian_radius(h, w) == pytest.approx(_centernet_radius(h, w), rel=1e-12)


def test_heatmap_and_regression_targets() -> None:
    boxes = np.array([[3.1, 8.2, 1.8, 4.6, 0.3], [-10.0, -5.05, 2.5, 12.0, -2.0], [4.0, -3.0, 6.0, 9.0, 1.0]])
    targets = build_targets([boxes], [np.array([4, 9, 2])], np.zeros((1, 3)), CFG)
    size, cell = CFG.feature_size, CFG.cell_size
    heatmap = targets["heatmap"][0]
    assert targets["heatmap"].shape == (1, size, size) and heatmap.dtype == np.float32
    centres = feature_cell_centres(size, CFG.input_size, CFG.resolution)
    for slot, box in enumerate(boxes):
        row, col = _cell(box[0], box[1])
        assert heatmap[row, col] == 1.0  # exactly
        assert targets["centre_index"][slot] == row * size + col and targets["box_mask"][slot] == 1
        # Decoding the targets gives the box back: cell centre + offset cells, exp(log size), atan2.
        centre = centres[row, col] + targets["offset"][slot] * cell
        np.testing.assert_allclose(centre, box[:2], atol=1e-5)
        assert np.all(np.abs(targets["offset"][slot]) <= 0.5)
        np.testing.assert_allclose(np.exp(targets["log_size"][slot]), box[2:4], rtol=1e-6)
        sin, cos = targets["rotation"][slot]
        assert math.atan2(sin, cos) == pytest.approx(box[4], abs=1e-6)
        np.testing.assert_allclose(targets["boxes"][slot], box, atol=1e-6)
    # Size-dependent radius: the big box's Gaussian is wider than the car's.
    radius_small = max(1, int(_centernet_radius(4.6 / cell, 1.8 / cell)))
    radius_big = max(1, int(_centernet_radius(9.0 / cell, 6.0 / cell)))
    assert radius_big > radius_small >= 1
    row, col = _cell(4.0, -3.0)
    sigma = (2 * radius_big + 1) / 6
    assert heatmap[row, col + radius_big] == pytest.approx(math.exp(-radius_big**2 / (2 * sigma**2)), rel=1e-6)
    assert heatmap[row, col + radius_big + 1] == 0.0  # the (2r+1)^2 window ends there
    assert targets["box_mask"][3:].sum() == 0 and np.all(targets["centre_index"][3:] == 0)
    assert targets["flow"].shape == (0, 2, size, size) and targets["flow_valid"].shape == (0, 1, size, size)


def test_more_objects_than_queries_are_dropped_with_a_warning(caplog: pytest.LogCaptureFixture) -> None:
    cfg = CFG.replace(head=HeadConfig(num_queries=4))
    boxes = np.array([[x, 2.0, 1.8, 4.5, 0.0] for x in (-8.0, -4.0, 0.0, 4.0, 8.0, 10.0)])
    with caplog.at_level(logging.WARNING, logger="rafd.targets"):
        targets = build_targets([boxes], [np.arange(6)], np.zeros((1, 3)), cfg)
    assert targets["box_mask"].tolist() == [1, 1, 1, 1] and "dropping 2" in caplog.text
    assert targets["heatmap"][0].max() == 1.0 and (targets["heatmap"][0] == 1.0).sum() == 4


def _region(row: int, col: int, radius: float, size: int) -> np.ndarray:
    i, j = np.meshgrid(np.arange(size), np.arange(size), indexing="ij")
    return np.hypot(i - row, j - col) <= radius


def test_flow_removes_ego_motion_and_marks_regions() -> None:
    """Ego drives 2 m forward and turns 5 degrees; object 1 is static in the world, object 2 moves
    1.5 m along world x, object 3 appears in frame 1. Expected flows computed from world coordinates."""
    yaw = math.radians(5.0)
    poses = np.array([[100.0, 50.0, 0.2], [0.0, 0.0, 0.0]])
    poses[1] = [100.0 - 2.0 * math.sin(0.2), 50.0 + 2.0 * math.cos(0.2), 0.2 + yaw]

    def to_ego(pose, world):
        c, s = math.cos(pose[2]), math.sin(pose[2])
        d = np.asarray(world) - pose[:2]
        return np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1]])

    world_0 = {1: np.array([104.0, 60.0]), 2: np.array([96.0, 58.0])}
    world_1 = {1: world_0[1], 2: world_0[2] + [1.5, 0.0], 3: np.array([101.0, 45.0])}
    frame0 = np.array([[*to_ego(poses[0], world_0[k]), 1.8, 4.5, 0.1] for k in (1, 2)])
    frame1 = np.array([[*to_ego(poses[1], world_1[k]), 1.8, 4.5, 0.1] for k in (1, 2, 3)])
    targets = build_targets([frame0, frame1], [np.array([1, 2]), np.array([1, 2, 3])], poses, CFG)
    flow, valid, fg = targets["flow"][0], targets["flow_valid"][0, 0], targets["flow_foreground"][0, 0]
    size = CFG.feature_size
    expected = np.zeros((2, size, size))
    moved = to_ego(poses[1], world_0[2] + [1.5, 0.0]) - to_ego(poses[1], world_0[2])  # world motion seen in frame 1
    regions = {}
    for k, box in zip((1, 2, 3), frame1):
        row, col = _cell(*box[:2])
        sigma = max(_centernet_radius(4.5 / CFG.cell_size, 1.8 / CFG.cell_size), FLOW_MIN_RADIUS)
        regions[k] = _region(row, col, sigma, size)
    expected[:, regions[2]] = moved[:, None]
    np.testing.assert_allclose(flow, expected, atol=1e-5)  # object 1 static: zero flow, like the background
    np.testing.assert_array_equal(fg, (regions[1] | regions[2]).astype(np.float32))
    np.testing.assert_array_equal(valid, (~regions[3]).astype(np.float32))  # new object: motion unknown
    assert regions[2].sum() >= 13  # a disc of radius gamma = 2 cells at least


def test_flow_for_every_consecutive_pair() -> None:
    boxes = [np.array([[0.0, 2.0 + t, 1.8, 4.5, 0.0]]) for t in range(4)]
    targets = build_targets(boxes, [np.array([7])] * 4, np.zeros((4, 3)), CFG)
    assert targets["flow"].shape == (3, 2, CFG.feature_size, CFG.feature_size)
    for pair in range(3):
        row, col = _cell(0.0, 3.0 + pair)
        np.testing.assert_allclose(targets["flow"][pair, :, row, col], [0.0, 1.0], atol=1e-6)
        assert targets["flow_foreground"][pair].sum() > 0 and targets["flow_valid"][pair].min() == 1.0
