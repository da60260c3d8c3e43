"""Cost-volume flow: zero for identical features, one cell for a known shift; the full branch runs."""

from __future__ import annotations

import torch

from rafd.model.align import cell_centres
from rafd.model.flow import flow_from_correlation, global_correlation

SIZE, FEATURES, RES = 64, 16, 0.5
CELL = SIZE / FEATURES * RES
N = FEATURES * FEATURES


def test_identical_features_give_zero_flow() -> None:
    grid = cell_centres(FEATURES, SIZE, RES)  # [N, 2]
    # equal-norm features: the dot product is largest with itself, and the scale makes the softmax peaked
    features = torch.nn.functional.normalize(torch.randn(2, N, 32), dim=-1) * 20
    flow = flow_from_correlation(global_correlation(features, features), grid)  # [2, N, 2]
    assert flow.abs().max() < 1e-3


def test_known_shift_gives_the_displacement_in_metres() -> None:
    grid = cell_centres(FEATURES, SIZE, RES)
    codes = torch.eye(N) * 30  # one orthogonal code per cell: a sharp, unambiguous match
    previous = codes.reshape(FEATURES, FEATURES, N)
    # content moved one cell right: current cell (i, j) shows what previous cell (i, j - 1) showed
    current = torch.roll(previous, shifts=1, dims=1)
    flow = flow_from_correlation(global_correlation(current.reshape(1, N, N), previous.reshape(1, N, N)), grid).reshape(
        FEATURES, FEATURES, 2
    )
    inner = flow[:, 1:]  # column 0 wrapped around
    torch.testing.assert_close(inner[..., 0], torch.full_like(inner[..., 0], CELL), atol=1e-4, rtol=0)
    torch.testing.assert_close(inner[..., 1], torch.zeros_like(inner[..., 1]), atol=1e-4, rtol=0)
