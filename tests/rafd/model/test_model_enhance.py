"""Window / shifted-window attention against an independent masked global attention."""

from __future__ import annotations

import math

import pytest
import torch

from rafd.model.enhance import build_enhancement, shifted_window_mask, window_attention

H, W, C = 8, 12, 6
WINDOW = (H // 2, W // 2)
SHIFT = (WINDOW[0] // 2, WINDOW[1] // 2)


def reference_attention(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, shift: tuple[int, int]) -> torch.Tensor:
    """Global attention where token p may see token q only inside the same window.

    Shifted windows, in the original (un-rolled) coordinates, are the tiles
    floor((row - shift) / wh) x floor((col - shift) / ww) without wrap-around: the pieces that the cyclic
    roll glues into one window stay apart, which is what Swin's mask achieves.
    """
    rows = torch.arange(H).repeat_interleave(W)  # [H*W]
    cols = torch.arange(W).repeat(H)  # [H*W]
    group = torch.div(rows - shift[0], WINDOW[0], rounding_mode="floor") * 1000 + torch.div(
        cols - shift[1], WINDOW[1], rounding_mode="floor"
    )
    allowed = group[:, None] == group[None, :]  # [H*W, H*W]
    scores = q @ k.transpose(1, 2) / math.sqrt(C)
    scores = scores.masked_fill(~allowed, float("-inf"))
    return scores.softmax(-1) @ v


@pytest.mark.parametrize("shifted", [False, True])
def test_window_attention_matches_masked_global_attention(shifted: bool) -> None:
    q, k, v = (torch.randn(2, H * W, C, dtype=torch.float64) for _ in range(3))
    shift = SHIFT if shifted else (0, 0)
    mask = shifted_window_mask(H, W, WINDOW, SHIFT).double() if shifted else None
    got = window_attention(q, k, v, size=(H, W), window=WINDOW, shift=shift, mask=mask)
    torch.testing.assert_close(got, reference_attention(q, k, v, shift), atol=1e-10, rtol=1e-10)


def test_enhancement_shapes_and_ablation_identity() -> None:
    features = torch.randn(2, 8, 16, 16)
    enhancement = build_enhancement(8, 16, num_blocks=2, ffn_ratio=2, enabled=True)
    out = enhancement(features)
    assert out.shape == features.shape and not torch.allclose(out, features)
    disabled = build_enhancement(8, 16, num_blocks=2, ffn_ratio=2, enabled=False)
    assert len(list(disabled.parameters())) == 0
    assert torch.equal(disabled(features), features)


def test_window_mask_is_a_static_buffer_outside_the_state_dict() -> None:
    enhancement = build_enhancement(8, 16, num_blocks=1, ffn_ratio=2, enabled=True)
    assert enhancement.blocks[0].mask.shape == (4, 64, 64)
    assert not any("mask" in key for key in enhancement.state_dict())
