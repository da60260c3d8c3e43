"""Speed options that change the mathematics (flow.stride, enhance.window): defaults are the paper's network,
the options build, train (every parameter gets a gradient), stream exactly like the window, and keep geometry."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from torch.nn import functional as F

from rafd.config import RaFDConfig
from rafd.model import build_model, relative_pose_torch
from rafd.model.align import cell_centres
from rafd.model.enhance import shifted_window_mask, window_attention


def options_config(make_config, num_frames: int = 4, stride: int = 8, window: int = 4) -> RaFDConfig:
    """The 64 px test network (16 x 16 cells) with the flow at stride 8 (8 x 8 matching cells) and 4 x 4 windows."""
    cfg = make_config(num_frames)
    return cfg.replace(
        flow=dataclasses.replace(cfg.flow, stride=stride), enhance=dataclasses.replace(cfg.enhance, window=window)
    )


def test_defaults_are_the_paper_network(make_config, make_inputs) -> None:
    """flow.stride = output_stride and enhance.window = Hf/2 spelled out give the default model, bit for bit."""
    assert RaFDConfig.paper().flow.stride == 4 and RaFDConfig.paper().enhance.window == 0
    assert RaFDConfig.paper().enhance_window == 32 and RaFDConfig.paper().flow_size == 64
    cfg = make_config(4)
    explicit = options_config(make_config, stride=cfg.output_stride, window=cfg.feature_size // 2)
    torch.manual_seed(3)
    default_model = build_model(cfg).eval()
    torch.manual_seed(3)
    explicit_model = build_model(explicit).eval()
    frames, poses = make_inputs(cfg, 1, seed=4)
    with torch.no_grad():
        a, b = default_model(frames, poses), explicit_model(frames, poses)
    for name in a:
        assert torch.equal(a[name], b[name]), name


def test_options_change_the_network_shapes_stay(make_config, make_inputs) -> None:
    cfg = options_config(make_config)
    model = build_model(cfg).eval()
    hf, hm, c = cfg.feature_size, cfg.flow_size, cfg.neck.channels
    assert (hf, hm) == (16, 8)
    assert model.flow.position.shape == (hm * hm, c // 2) and model.flow.centres.shape == (hm * hm, 2)
    assert model.encoder.enhancement.blocks[0].mask.shape == (16, 16, 16)  # 4 x 4 windows of 4 x 4 cells
    frames, poses = make_inputs(cfg, 2, seed=1)
    with torch.no_grad():
        features = model.encode_frame(frames[:, 0])
        assert model.flow.encode(features).shape == (2, c // 2, hm, hm)
        out = model(frames, poses)
    assert out["flow"].shape == (2, 3, 2, hf, hf) and torch.isfinite(out["flow"]).all()
    assert out["heatmap"].shape == (2, 1, hf, hf)
    assert out["boxes"].shape == (2, cfg.head.num_queries, 5) and torch.isfinite(out["boxes"]).all()
    # the options really change the mathematics
    paper_style = build_model(make_config(4)).eval()
    paper_style.load_state_dict(model.state_dict())  # same parameters: the options add none
    with torch.no_grad():
        other = paper_style(frames, poses)
    assert not torch.allclose(other["flow"], out["flow"])


def test_gradients_reach_every_parameter_with_the_options(make_config, make_inputs) -> None:
    cfg = options_config(make_config)
    model = build_model(cfg).train()
    with torch.no_grad():  # some inits are exact zeros; jitter so the check is about the graph
        for parameter in model.parameters():
            parameter.add_(torch.randn_like(parameter) * 0.05)
    frames, poses = make_inputs(cfg, 2)
    out = model(frames, poses)
    loss = (
        out["heatmap"].sigmoid().mean()
        + out["flow"].abs().mean()
        + sum(out[n].square().mean() for n in ("pred_offset", "pred_log_size", "pred_rotation"))
    )
    loss.backward()
    bad = [
        n
        for n, p in model.named_parameters()
        if p.grad is None or not torch.isfinite(p.grad).all() or p.grad.abs().sum() == 0
    ]
    assert not bad, bad


def test_streaming_equals_the_window_with_the_options(make_config, make_inputs) -> None:
    cfg = options_config(make_config)
    model = build_model(cfg).eval()
    frames, poses = make_inputs(cfg, 2, seed=2)
    with torch.no_grad():
        window = model(frames, poses)
        features = torch.stack([model.encode_frame(frames[:, t]) for t in range(4)], dim=1)
        flows = torch.stack(
            [
                model.pair_flow(features[:, t - 1], features[:, t], relative_pose_torch(poses[:, t - 1], poses[:, t]))
                for t in range(1, 4)
            ],
            1,
        )
        streamed = model.detect(features, flows, poses)
    torch.testing.assert_close(flows, window["flow"], atol=1e-5, rtol=1e-5)
    assert torch.equal(streamed["query_indices"], window["query_indices"])
    for name in ("heatmap", "scores", "boxes"):
        torch.testing.assert_close(streamed[name], window[name], atol=1e-5, rtol=1e-5, msg=name)


def test_upsampled_coarse_grid_lands_on_the_fine_cell_centres() -> None:
    """Bilinear x2 (half-pixel) of the coarse cells' metres gives the fine cells' metres away from the border:
    the coarse grid (avg-pooled cells) and the upsampling agree with the detection grid's geometry."""
    fine, coarse = cell_centres(16, 64, 0.5), cell_centres(8, 64, 0.5)  # [N, 2] metres
    as_map = coarse.reshape(1, 8, 8, 2).permute(0, 3, 1, 2)  # [1, 2, 8, 8]
    up = F.interpolate(as_map, size=(16, 16), mode="bilinear", align_corners=False)[0].permute(1, 2, 0)  # [16, 16, 2]
    torch.testing.assert_close(up[1:-1, 1:-1], fine.reshape(16, 16, 2)[1:-1, 1:-1], atol=1e-5, rtol=0)
    pooled = F.avg_pool2d(fine.reshape(1, 16, 16, 2).permute(0, 3, 1, 2), 2)[0].permute(1, 2, 0)  # [8, 8, 2]
    torch.testing.assert_close(pooled, coarse.reshape(8, 8, 2), atol=1e-5, rtol=0)


def _masked_global_attention(q, k, v, size, window, shift):
    """Global attention where tokens see each other only inside the same (shifted, non-wrapping) window."""
    rows = torch.arange(size[0]).repeat_interleave(size[1])
    cols = torch.arange(size[1]).repeat(size[0])
    group = torch.div(rows - shift[0], window[0], rounding_mode="floor") * 1000 + torch.div(
        cols - shift[1], window[1], rounding_mode="floor"
    )
    scores = q @ k.transpose(1, 2) / math.sqrt(q.shape[-1])
    return scores.masked_fill(group[:, None] != group[None, :], float("-inf")).softmax(-1) @ v


@pytest.mark.parametrize("shifted", [False, True])
def test_small_windows_match_masked_global_attention(shifted: bool) -> None:
    """3 x 4 windows of 4 x 4 cells on a 12 x 16 map (the option's case: more than 2 windows per side)."""
    size, window = (12, 16), (4, 4)
    shift = (2, 2) if shifted else (0, 0)
    q, k, v = (torch.randn(2, size[0] * size[1], 5, dtype=torch.float64) for _ in range(3))
    mask = shifted_window_mask(*size, window, (2, 2)).double() if shifted else None
    got = window_attention(q, k, v, size=size, window=window, shift=shift, mask=mask)
    torch.testing.assert_close(got, _masked_global_attention(q, k, v, size, window, shift), atol=1e-10, rtol=1e-10)


@pytest.mark.parametrize(
    "change",
    [
        {"flow": {"stride": 6}},  # not a multiple of output_stride
        {"flow": {"stride": 24}},  # does not divide input_size 64
        {"enhance": {"window": 3}},  # odd: no half-window shift
        {"enhance": {"window": 6}},  # does not tile 16 cells
    ],
)
def test_bad_options_are_refused(make_config, change) -> None:
    cfg = make_config(4)
    ((part, values),) = change.items()
    with pytest.raises(ValueError):
        cfg.replace(**{part: dataclasses.replace(getattr(cfg, part), **values)})


def test_options_survive_the_config_json(make_config) -> None:
    cfg = options_config(make_config)
    assert RaFDConfig.from_json(cfg.to_json()) == cfg
    partial = cfg.to_dict()  # a stored config names every field: one lacking a field is refused, never defaulted
    del partial["flow"]["stride"], partial["enhance"]["window"]
    with pytest.raises(ValueError, match="missing"):
        RaFDConfig.from_dict(partial)
