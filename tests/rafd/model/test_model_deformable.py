"""Deformable sampling = bilinear lookup; flow-guided reference points move against the flow."""

from __future__ import annotations

import math

import torch
from torch import nn

from rafd.model.align import cell_centres
from rafd.model.deformable import DeformableAttention, DeformableLayer, deformable_sample
from rafd.model.propagation import FlowGuidedPropagation

SIZE, FEATURES, RES = 64, 16, 0.5
CELL = SIZE / FEATURES * RES
HALF = SIZE * RES / 2


def bilinear(value: torch.Tensor, x: float, y: float) -> torch.Tensor:
    """Hand-written grid_sample (align_corners=False, zeros outside) at one normalised point: [C, H, W] -> [C]."""
    channels, height, width = value.shape
    u, v = ((x + 1) * width - 1) / 2, ((y + 1) * height - 1) / 2  # continuous (col, row), centres at integers
    u0, v0 = math.floor(u), math.floor(v)
    out = torch.zeros(channels, dtype=value.dtype)
    for row, wy in ((v0, 1 - (v - v0)), (v0 + 1, v - v0)):
        for col, wx in ((u0, 1 - (u - u0)), (u0 + 1, u - u0)):
            if 0 <= row < height and 0 <= col < width:
                out += wx * wy * value[:, row, col]
    return out


def test_deformable_sample_is_a_weighted_bilinear_lookup() -> None:
    value = torch.randn(1, 3, 5, 7, dtype=torch.float64)
    points = torch.tensor(
        [[[[0.1, -0.3], [-0.95, 0.9], [0.99, 0.2]], [[0.0, 0.0], [0.5, 0.5], [-1.2, 0.0]]]], dtype=torch.float64
    )
    weights = torch.tensor([[[0.2, 0.3, 0.5], [0.6, 0.1, 0.3]]], dtype=torch.float64)
    got = deformable_sample(value, points, weights)  # [1, 2, 3]
    for q in range(2):
        expected = sum(weights[0, q, p] * bilinear(value[0], *points[0, q, p].tolist()) for p in range(3))
        torch.testing.assert_close(got[0, q], expected, atol=1e-12, rtol=0)


def identity_propagation(flow_guided: bool = True) -> FlowGuidedPropagation:
    """One layer whose attention reads exactly its reference point and copies the value through."""
    attention = DeformableAttention(4, num_points=3, map_size=(FEATURES, FEATURES))
    with torch.no_grad():
        attention.sampling_offsets.bias.zero_()  # every point at the reference
        attention.value_proj.weight.copy_(torch.eye(4)[:, :, None, None])
        attention.output_proj.weight.copy_(torch.eye(4))
    return FlowGuidedPropagation(
        [DeformableLayer(attention, 4, 2)], cell_centres(FEATURES, SIZE, RES), HALF, flow_guided
    )


def test_zero_flow_and_identity_pose_sample_at_the_own_cell() -> None:
    propagation = identity_propagation()
    reference = propagation.reference_points(torch.zeros(2, 2, FEATURES, FEATURES))  # [2, Hf*Wf, 2]
    rows, cols = torch.meshgrid(torch.arange(FEATURES), torch.arange(FEATURES), indexing="ij")
    own = torch.stack([(cols + 0.5) / FEATURES * 2 - 1, (rows + 0.5) / FEATURES * 2 - 1], -1).reshape(-1, 2)
    torch.testing.assert_close(reference, own[None].expand(2, -1, -1))
    previous = torch.randn(2, 4, FEATURES, FEATURES)
    layer = propagation.layers[0]
    read = layer.attention(torch.randn(2, FEATURES**2, 4), reference, previous)  # [2, Hf*Wf, 4]
    torch.testing.assert_close(read, previous.flatten(2).transpose(1, 2), atol=1e-5, rtol=0)


def test_flow_moves_the_reference_back_to_where_the_content_was() -> None:
    propagation = identity_propagation()
    previous = torch.randn(1, 4, FEATURES, FEATURES)
    layer = propagation.layers[0]
    query = torch.randn(1, FEATURES**2, 4)
    # content moved one cell right (+x) and one cell forward (+y = one row up) since the previous frame
    flow = torch.zeros(1, 2, FEATURES, FEATURES)
    flow[:, 0], flow[:, 1] = CELL, CELL
    read = layer.attention(query, propagation.reference_points(flow), previous)  # [1, Hf*Wf, 4]
    read = read.transpose(1, 2).reshape(1, 4, FEATURES, FEATURES)
    # cell (i, j) reads the previous map at (i + 1, j - 1)
    torch.testing.assert_close(read[:, :, :-1, 1:], previous[:, :, 1:, :-1], atol=1e-5, rtol=0)
    # the vanilla ablation ignores the flow
    vanilla = identity_propagation(flow_guided=False)
    torch.testing.assert_close(vanilla.reference_points(flow), propagation.reference_points(torch.zeros_like(flow)))


def test_propagation_runs_end_to_end() -> None:
    propagation = identity_propagation()
    current, previous = torch.randn(2, 4, FEATURES, FEATURES), torch.randn(2, 4, FEATURES, FEATURES)
    out = propagation(current, previous, torch.zeros(2, 2, FEATURES, FEATURES), torch.zeros(2, 3))
    assert out.shape == current.shape and torch.isfinite(out).all()
    assert isinstance(propagation.layers[0].ffn, nn.Module)
