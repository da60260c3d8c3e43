"""The local cost volume (flow.local_radius): a shifted copy of a map is found at its true displacement, offsets
leaving the map never match, a window is cut symmetrically at the edge (a flat match gives zero flow there), and a
static scene gives zero flow."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")

from rafd.model.flow import (  # noqa: E402 - after the torch skip
    flow_from_local_correlation,
    local_correlation,
    local_offsets,
    shift_kernels,
    symmetric_window_mask,
)


def flow_of(previous, current, radius: int, cell: float = 1.0):  # noqa: ANN001, ANN201 - tensors
    channels, size = previous.shape[1], previous.shape[-1]
    correlation = local_correlation(current, previous, shift_kernels(channels, radius)) * 50.0  # sharpen
    return flow_from_local_correlation(correlation, local_offsets(radius, cell), symmetric_window_mask(size, radius))


def test_a_shifted_map_is_found_at_its_displacement() -> None:
    torch.manual_seed(0)
    previous = torch.randn(1, 64, 16, 16)  # enough channels that the true match is the best one
    # content moved 2 columns right and 1 row up (+x, +y forward): current[i, j] = previous[i + 1, j - 2]
    current = torch.roll(previous, shifts=(-1, 2), dims=(2, 3))
    flow = flow_of(previous, current, radius=3, cell=0.5)
    inner = flow[0, :, 4:-4, 4:-4]
    assert torch.allclose(inner[0], torch.full_like(inner[0], 2 * 0.5), atol=1e-3)  # x: 2 cells right
    assert torch.allclose(inner[1], torch.full_like(inner[1], 1 * 0.5), atol=1e-3)  # y: 1 cell forward


def test_a_static_scene_has_zero_flow_to_the_edge() -> None:
    torch.manual_seed(1)
    frame = torch.randn(1, 64, 12, 12)
    flow = flow_of(frame, frame, radius=2)
    assert flow.abs().max() < 1e-3  # edge cells included: outside offsets are masked, not matched to padding


def test_the_mask_cuts_the_window_to_the_same_reach_on_both_sides() -> None:
    mask = symmetric_window_mask(5, 1)  # [1, 9, 5, 5], offsets row-major from (-1, -1)
    assert mask.shape == (1, 9, 5, 5)
    assert mask[0, 4].abs().max() == 0  # zero offset: always allowed
    assert (mask[0, 0, 0, :] < 0).all() and (mask[0, 0, 1:4, 1:4] == 0).all()  # (-1, -1): off on the outer ring
    assert (mask[0, 8, -1, :] < 0).all() and (mask[0, 8, :, 0] < 0).all()  # (+1, +1): off on the opposite side too


def test_a_featureless_scene_has_zero_flow_at_the_edge() -> None:
    # every offset equally good (an empty road): the expectation over a one-sided window would point inwards
    flat = torch.zeros(1, 1, 25, 12, 12)
    flow = flow_from_local_correlation(flat[:, 0], local_offsets(2, 1.0), symmetric_window_mask(12, 2))
    assert flow.abs().max() < 1e-5
