"""encode_frame / pair_flow / detect compose to forward: a stream that caches them equals the window."""

from __future__ import annotations

import pytest
import torch

from rafd.model import build_model, relative_pose_torch


def assert_outputs_equal(got: dict, expected: dict) -> None:
    assert got.keys() == expected.keys()
    for name in expected:
        if name == "query_indices":
            assert torch.equal(got[name], expected[name])
        else:
            torch.testing.assert_close(got[name], expected[name], atol=1e-5, rtol=1e-5, msg=name)


@pytest.mark.parametrize("num_frames", [1, 2, 4])
def test_streaming_steps_equal_forward(make_config, make_inputs, num_frames: int) -> None:
    cfg = make_config(num_frames)
    model = build_model(cfg).eval()
    frames, poses = make_inputs(cfg, 2, seed=1)
    with torch.no_grad():
        window = model(frames, poses)
        features = torch.stack([model.encode_frame(frames[:, t]) for t in range(num_frames)], dim=1)
        assert features.shape == (2, num_frames, cfg.neck.channels, cfg.feature_size, cfg.feature_size)
        flows = None
        if num_frames > 1:
            flows = torch.stack(
                [
                    model.pair_flow(
                        features[:, t - 1], features[:, t], relative_pose_torch(poses[:, t - 1], poses[:, t])
                    )
                    for t in range(1, num_frames)
                ],
                dim=1,
            )
        streamed = model.detect(features, flows, poses)
    if flows is not None:
        streamed["flow"] = flows
    assert_outputs_equal(streamed, window)


def test_sliding_window_reuses_cached_features(make_config, make_inputs) -> None:
    """Frame 5 arrives: only its features and the (4, 5) flow are new; the result equals the window [2..5]."""
    cfg = make_config(4)
    model = build_model(cfg).eval()
    cfg5 = cfg.replace(num_frames=2)  # make_inputs needs T; build a 5-frame sequence from two draws
    frames_a, poses_a = make_inputs(cfg, 1, seed=2)
    frames_b, poses_b = make_inputs(cfg5, 1, seed=3)
    frames = torch.cat([frames_a, frames_b[:, :1]], dim=1)  # [1, 5, 1, S, S]
    poses = torch.cat([poses_a, poses_a[:, -1:] + torch.tensor([0.1, 1.4, 0.02])], dim=1)  # [1, 5, 3]
    with torch.no_grad():
        cache = [model.encode_frame(frames[:, t]) for t in range(4)]
        pair = [
            model.pair_flow(cache[t - 1], cache[t], relative_pose_torch(poses[:, t - 1], poses[:, t]))
            for t in range(1, 4)
        ]
        newest = model.encode_frame(frames[:, 4])
        pair.append(model.pair_flow(cache[3], newest, relative_pose_torch(poses[:, 3], poses[:, 4])))
        streamed = model.detect(torch.stack(cache[1:] + [newest], 1), torch.stack(pair[1:], 1), poses[:, 1:])
        window = model(frames[:, 1:], poses[:, 1:])
    window.pop("flow")
    assert_outputs_equal(streamed, window)
