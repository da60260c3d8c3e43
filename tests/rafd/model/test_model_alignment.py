"""Ego-motion alignment: relative_pose_torch twins rafd.geometry, align_to_current resamples correctly."""

from __future__ import annotations

import numpy as np
import torch

from rafd import geometry
from rafd.model import relative_pose_torch
from rafd.model.align import align_to_current, cell_centres

SIZE, FEATURES, RES = 64, 16, 0.5  # 16 x 16 cells of 2 m, half extent 16 m
CELL = SIZE / FEATURES * RES
HALF = SIZE * RES / 2


def test_relative_pose_matches_geometry() -> None:
    rng = np.random.default_rng(3)
    a = rng.normal(size=(20, 3)) * [30, 30, 3]
    b = rng.normal(size=(20, 3)) * [30, 30, 3]
    expected = np.stack([geometry.relative_pose(x, y) for x, y in zip(a, b)])
    got = relative_pose_torch(torch.from_numpy(a), torch.from_numpy(b)).numpy()
    np.testing.assert_allclose(got, expected, atol=1e-9)


def world_field(points: np.ndarray) -> np.ndarray:
    """[..., 2] world metres -> [..., 3] channels: two affine (bilinear reproduces them exactly), one smooth."""
    x, y = points[..., 0], points[..., 1]
    return np.stack([0.3 * x - 0.2 * y + 1.0, 0.1 * x + 0.5 * y, np.sin(0.05 * x) * np.cos(0.04 * y)], axis=-1)


def feature_map(pose: np.ndarray) -> torch.Tensor:
    """The world field seen from an ego pose: -> [1, 3, Hf, Wf]."""
    centres = geometry.feature_cell_centres(FEATURES, SIZE, RES)  # [Hf, Wf, 2]
    values = world_field(geometry.transform_points(pose, centres))  # [Hf, Wf, 3]
    return torch.from_numpy(values).permute(2, 0, 1)[None].float()


def test_aligned_previous_equals_current_in_range_and_current_outside() -> None:
    pose_prev = np.array([10.0, -4.0, 0.3])
    pose_cur = np.array([13.0, 3.0, 0.45])  # 7.6 m and 8.6 degrees of ego motion: part of the map leaves view
    previous, current = feature_map(pose_prev), feature_map(pose_cur)
    relative = torch.from_numpy(geometry.relative_pose(pose_prev, pose_cur))[None].float()
    aligned = align_to_current(previous, current, relative, cell_centres(FEATURES, SIZE, RES), HALF)[0]

    # Independent expectation: where each current cell centre lies in the previous ego frame.
    centres = geometry.feature_cell_centres(FEATURES, SIZE, RES)
    in_previous = geometry.transform_points(geometry.relative_pose(pose_cur, pose_prev), centres)  # [Hf, Wf, 2]
    span = HALF - CELL / 2  # the previous map's outermost cell centres
    distance = np.abs(in_previous).max(-1) - span
    inside, outside = distance < -1e-3, distance > 1e-3
    assert inside.sum() > 50 and outside.sum() > 20
    inside_t, outside_t = torch.from_numpy(inside), torch.from_numpy(outside)
    # affine channels are interpolated exactly, the smooth one nearly
    torch.testing.assert_close(aligned[:2][:, inside_t], current[0, :2][:, inside_t], atol=1e-4, rtol=1e-5)
    torch.testing.assert_close(aligned[2][inside_t], current[0, 2][inside_t], atol=5e-3, rtol=0)
    assert torch.equal(aligned[:, outside_t], current[0][:, outside_t])


def test_identity_pose_returns_previous_exactly() -> None:
    previous, current = torch.randn(2, 5, FEATURES, FEATURES), torch.randn(2, 5, FEATURES, FEATURES)
    aligned = align_to_current(previous, current, torch.zeros(2, 3), cell_centres(FEATURES, SIZE, RES), HALF)
    torch.testing.assert_close(aligned, previous, atol=1e-6, rtol=0)


def test_whole_cell_translation_shifts_the_map() -> None:
    previous = torch.randn(1, 4, FEATURES, FEATURES)
    current = torch.randn(1, 4, FEATURES, FEATURES)
    # the ego moved 2 cells forward (+y): a static point is 2 cells further back (lower rows) now
    pose_prev, pose_cur = np.zeros(3), np.array([0.0, 2 * CELL, 0.0])
    relative = torch.from_numpy(geometry.relative_pose(pose_prev, pose_cur))[None].float()
    aligned = align_to_current(previous, current, relative, cell_centres(FEATURES, SIZE, RES), HALF)
    torch.testing.assert_close(aligned[:, :, 2:], previous[:, :, :-2], atol=1e-5, rtol=0)
    assert torch.equal(aligned[:, :, :2], current[:, :, :2])  # new ground ahead: not in the previous scan
