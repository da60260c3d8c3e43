"""build_targets: CenterNet heatmap, regression targets with K padding, pseudo-GT flow with ego motion removed."""

from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np
import pytest
import torch

from rafd.config import HeadConfig, RaFDConfig, TargetConfig
from rafd.data.targets import build_targets, canonical_boxes, gaussian_radius
from rafd.geometry import box_corners, feature_cell_centres
from rafd.model.boxes import decode_boxes

CFG = RaFDConfig.tiny(input_size=128)  # 32 x 32 cells of 0.694 m, K = 32
FLOW_MIN_RADIUS = CFG.targets.flow_min_radius
# The targets before box_encoding / TargetConfig existed: (sin yaw, cos yaw), sizes as labelled, radius 0.7 / 1.
LEGACY = CFG.replace(
    head=dataclasses.replace(CFG.head, box_encoding="as_labelled"),
    targets=TargetConfig(heatmap_min_overlap=0.7, heatmap_min_radius=1),
)


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


def test_heatmap_and_regression_targets_as_labelled() -> None:
    boxes = np.array([[3.1, 8.2, 1.8, 4.6, 0.3], [-10.0, -5.05, 2.5, 12.0, -2.0], [4.0, -3.0, 6.0, 9.0, 1.0]])
    targets = build_targets([boxes], [np.array([4, 9, 2])], np.zeros((1, 3)), LEGACY)
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
    assert heatmap[row, col + radius_big] == pytest.approx(math.exp(-(radius_big**2) / (2 * sigma**2)), rel=1e-6)
    assert heatmap[row, col + radius_big + 1] == 0.0  # the (2r+1)^2 window ends there
    assert targets["box_mask"][3:].sum() == 0 and np.all(targets["centre_index"][3:] == 0)
    assert targets["flow"].shape == (0, 2, size, size) and targets["flow_valid"].shape == (0, 1, size, size)


def _same_rectangle(a: np.ndarray, b: np.ndarray) -> None:
    """Two boxes cover the same rectangle: their corner sets agree (in any order)."""
    ca, cb = box_corners(a)[0], box_corners(b)[0]
    distances = np.linalg.norm(ca[:, None] - cb[None], axis=-1)
    assert distances.min(axis=1).max() < 1e-6


def test_canonical_boxes_keep_the_rectangle_with_width_at_most_length() -> None:
    rng = np.random.default_rng(0)
    boxes = np.column_stack([rng.normal(0, 5, (50, 2)), rng.uniform(0.5, 13, (50, 2)), rng.uniform(-7, 7, 50)])
    canonical = canonical_boxes(boxes)
    assert np.all(canonical[:, 2] <= canonical[:, 3])
    assert np.all((canonical[:, 4] >= -np.pi / 2) & (canonical[:, 4] < np.pi / 2))
    for a, b in zip(boxes, canonical):
        _same_rectangle(a, b)


def test_symmetric_targets_are_the_same_for_every_labelling_of_one_rectangle() -> None:
    """RADIATE's annotators flip yaw by 180 degrees and swap width/length within a track: one target for all four."""
    box = np.array([3.1, 8.2, 1.8, 4.6, 0.3])
    labellings = [
        box,
        box + [0, 0, 0, 0, np.pi],
        [3.1, 8.2, 4.6, 1.8, 0.3 + np.pi / 2],
        [3.1, 8.2, 4.6, 1.8, 0.3 - np.pi / 2],
    ]
    targets = [build_targets([np.array([b])], [np.array([1])], np.zeros((1, 3)), CFG) for b in labellings]
    for other in targets[1:]:
        for key in ("heatmap", "offset", "log_size", "rotation"):
            np.testing.assert_allclose(other[key], targets[0][key], atol=1e-6)
    # ... and decoding the target (decode_boxes, "symmetric") gives that rectangle back, canonical
    slot = targets[0]
    size = CFG.feature_size
    index = int(slot["centre_index"][0])
    centre = torch.tensor(feature_cell_centres(size, CFG.input_size, CFG.resolution).reshape(-1, 2)[index])
    decoded = (
        decode_boxes(
            centre[None, None].float(),
            torch.tensor(slot["offset"][None, :1]),
            torch.tensor(slot["log_size"][None, :1]),
            torch.tensor(slot["rotation"][None, :1]),
            CFG.cell_size,
            "symmetric",
        )[0, 0]
        .double()
        .numpy()
    )
    np.testing.assert_allclose(decoded, canonical_boxes(box)[0], atol=1e-5)
    _same_rectangle(decoded, box)


def test_decoding_a_longer_width_returns_the_canonical_box() -> None:
    """The network may regress width > length: decoding swaps them and turns the box by 90 degrees."""
    log_size = torch.log(torch.tensor([[[4.0, 2.0]]]))
    angle = torch.tensor(0.8)  # 2 * yaw
    rotation = torch.stack([torch.sin(angle), torch.cos(angle)])[None, None]
    box = decode_boxes(torch.zeros(1, 1, 2), torch.zeros(1, 1, 2), log_size, rotation, 1.0, "symmetric")[0, 0]
    assert box[2].item() == pytest.approx(2.0) and box[3].item() == pytest.approx(4.0)
    assert box[4].item() == pytest.approx(0.4 + math.pi / 2 - math.pi)  # 0.4 + 90 deg, wrapped into [-90, 90)
    _same_rectangle(box.double().numpy(), np.array([0.0, 0.0, 4.0, 2.0, 0.4]))


def test_heatmap_radius_follows_centerpoint() -> None:
    """CenterPoint / CenterFormer: radius max(2, int(gaussian_radius(l, w, 0.1))); the old 0.7 / 1 gave a car 1 cell."""
    car = np.array([[0.0, 0.0, 1.9, 4.6, 0.0]])  # centre at a cell corner: cell (16, 16) of 32
    new = build_targets([car], [np.array([1])], np.zeros((1, 3)), CFG)["heatmap"][0]
    old = build_targets([car], [np.array([1])], np.zeros((1, 3)), LEGACY)["heatmap"][0]
    cell = CFG.cell_size
    expected = max(2, int(_centernet_radius(4.6 / cell, 1.9 / cell, 0.1)))
    assert max(1, int(_centernet_radius(4.6 / cell, 1.9 / cell))) == 1  # the old radius
    assert (old > 0).sum() == 9  # a 3 x 3 blob
    assert (new > 0).sum() == (2 * expected + 1) ** 2 and expected >= 2


def test_objects_beyond_the_queries_stay_heatmap_peaks_without_box_targets(caplog: pytest.LogCaptureFixture) -> None:
    cfg = CFG.replace(head=HeadConfig(num_queries=4))
    boxes = np.array([[x, 2.0, 1.8, 4.5, 0.0] for x in (-8.0, -4.0, 0.0, 4.0, 8.0, 10.0)])
    with caplog.at_level(logging.WARNING, logger="rafd.data.targets"):
        targets = build_targets([boxes], [np.arange(6)], np.zeros((1, 3)), cfg)
    assert targets["box_mask"].tolist() == [1, 1, 1, 1] and "2 get no box target" in caplog.text
    # a car beyond the K box slots is still a car: a peak, not a negative the heatmap loss pushes down
    assert targets["heatmap"][0].max() == 1.0 and (targets["heatmap"][0] == 1.0).sum() == 6


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
