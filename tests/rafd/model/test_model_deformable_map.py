"""The propagation's channel-major path (every map cell a query: Linear as 1x1 conv, LayerNorm over channels,
points-major sampling with the weighting fused) computes exactly the token-major DeformableLayer."""

from __future__ import annotations

import torch

from rafd.model.deformable import (
    DeformableAttention,
    DeformableLayer,
    deformable_sample,
    deformable_sample_points_major,
    layer_norm_on_map,
    linear_on_map,
)


def test_points_major_sampling_equals_the_token_major_one() -> None:
    value = torch.randn(2, 3, 6, 5, dtype=torch.float64)
    locations = torch.rand(2, 7, 4, 2, dtype=torch.float64) * 2.4 - 1.2  # [B, Q, P, 2], some outside the map
    weights = torch.rand(2, 7, 4, dtype=torch.float64).softmax(-1)  # [B, Q, P]
    token_major = deformable_sample(value, locations, weights)  # [B, Q, C]
    points_major = deformable_sample_points_major(
        value, locations.transpose(1, 2), weights.transpose(1, 2)
    )  # [B, C, Q]
    torch.testing.assert_close(points_major, token_major.transpose(1, 2), atol=1e-12, rtol=0)


def test_linear_and_layer_norm_on_a_map_equal_the_token_modules() -> None:
    linear, norm = torch.nn.Linear(5, 3).double(), torch.nn.LayerNorm(5).double()
    with torch.no_grad():
        norm.weight.uniform_(0.5, 1.5)
        norm.bias.uniform_(-0.5, 0.5)
    x = torch.randn(2, 5, 4, 6, dtype=torch.float64)  # [B, C, H, W]
    tokens = x.flatten(2).transpose(1, 2)  # [B, H*W, C]
    torch.testing.assert_close(linear_on_map(linear, x).flatten(2).transpose(1, 2), linear(tokens), atol=1e-12, rtol=0)
    torch.testing.assert_close(layer_norm_on_map(norm, x).flatten(2).transpose(1, 2), norm(tokens), atol=1e-12, rtol=0)


def test_forward_map_equals_forward_on_every_cell() -> None:
    torch.manual_seed(0)
    channels, size = 8, 6
    layer = DeformableLayer(DeformableAttention(channels, 4, (size, size)), channels, 2).double().eval()
    with torch.no_grad():
        for parameter in layer.parameters():  # leave the init's zeros and identities: a generic layer
            parameter.add_(torch.randn_like(parameter) * 0.2)
    query = torch.randn(2, channels, size, size, dtype=torch.float64)
    reference = torch.rand(2, size * size, 2, dtype=torch.float64) * 2 - 1
    value = torch.randn(2, channels, size, size, dtype=torch.float64)
    tokens = layer(query.flatten(2).transpose(1, 2), reference, value)  # [B, Q, C]
    maps = layer.forward_map(query, reference, value)  # [B, C, H, W]
    torch.testing.assert_close(maps.flatten(2).transpose(1, 2), tokens, atol=1e-12, rtol=0)


def test_a_fresh_pre_norm_layer_is_the_identity_and_a_trained_one_is_not() -> None:
    torch.manual_seed(1)
    channels, size = 8, 6
    layer = DeformableLayer(DeformableAttention(channels, 4, (size, size)), channels, 2, norm="pre").double().eval()
    query = torch.randn(2, channels, size, size, dtype=torch.float64)
    reference = torch.rand(2, size * size, 2, dtype=torch.float64) * 2 - 1
    value = torch.randn(2, channels, size, size, dtype=torch.float64)
    torch.testing.assert_close(layer.forward_map(query, reference, value), query, atol=0, rtol=0)
    tokens = query.flatten(2).transpose(1, 2)  # [B, Q, C]
    torch.testing.assert_close(layer(tokens, reference, value), tokens, atol=0, rtol=0)
    with torch.no_grad():
        for parameter in layer.parameters():
            parameter.add_(torch.randn_like(parameter) * 0.2)
    maps = layer.forward_map(query, reference, value)
    assert (maps - query).abs().max() > 0.1  # the branches now add something ...
    # ... and the channel-major path still computes the token-major layer, un-normalised residual stream included
    torch.testing.assert_close(maps.flatten(2).transpose(1, 2), layer(tokens, reference, value), atol=1e-12, rtol=0)


def test_post_norm_stays_the_default_and_unknown_norms_are_refused() -> None:
    import pytest

    layer = DeformableLayer(DeformableAttention(8, 4, (6, 6)), 8, 2)
    assert not layer.pre_norm and layer.attention.output_proj.weight.abs().sum() > 0
    with pytest.raises(ValueError, match="norm"):
        DeformableLayer(DeformableAttention(8, 4, (6, 6)), 8, 2, norm="sandwich")
