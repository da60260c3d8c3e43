"""Every parameter takes part in the training graph (also required by DDP without find_unused_parameters)."""

from __future__ import annotations

import pytest
import torch

from rafd.model import build_model


@pytest.mark.parametrize("num_frames", [1, 4])
def test_gradients_reach_every_parameter(make_config, make_inputs, num_frames: int) -> None:
    cfg = make_config(num_frames)
    model = build_model(cfg).train()
    # Some inits are exact zeros (last BN scale of a residual block, deformable offset weights), which
    # would block gradients at step 0 only; jitter every parameter so the check is about the graph.
    with torch.no_grad():
        for parameter in model.parameters():
            parameter.add_(torch.randn_like(parameter) * 0.05)
    frames, poses = make_inputs(cfg, 2)
    k = cfg.head.num_queries
    gt_indices = torch.randint(0, cfg.feature_size**2, (2, k))
    gt_mask = (torch.arange(k) < 3).float().expand(2, -1)
    out = model(frames, poses, gt_indices=gt_indices, gt_mask=gt_mask)
    loss = out["heatmap"].sigmoid().mean() + sum(
        out[n].square().mean() for n in ("pred_offset", "pred_log_size", "pred_rotation")
    )
    if num_frames > 1:
        loss = loss + out["flow"].abs().mean()
    loss.backward()
    missing = [name for name, p in model.named_parameters() if p.grad is None or not torch.isfinite(p.grad).all()]
    zero = [name for name, p in model.named_parameters() if p.grad is not None and p.grad.abs().sum() == 0]
    assert not missing, missing
    assert not zero, zero
