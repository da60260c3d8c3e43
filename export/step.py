"""The torch modules that are exported: the streaming step graph and the full-window graph.

Both are thin wrappers over the model's own streaming decomposition (encode_frame / pair_flow / detect), so the
step graph computes exactly what model.forward computes for the window whose caches it is given.
Input and output names and shapes are the contract of rafd.runtime (see its docstring).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor, nn

from rafd.config import RaFDConfig
from rafd.model import RaFD, relative_pose_torch
from rafd.runtime import FORMS


class Method(nn.Module):
    """A bound method of the model called as a module, so that the ONNX exporter names its nodes after this module.

    The TorchScript exporter scopes a node by the modules whose __call__ is on the stack: a model method called
    directly (model.flow_features, model.pair_flow_encoded) gets its caller's scope, and its operations would land
    outside any module in a by-module profile (rafd bench speed --profile). The method is kept as a plain attribute,
    not a submodule: the graph's parameters and state dict are the model's, unchanged."""

    def __init__(self, method: Callable[..., Tensor]) -> None:
        super().__init__()
        self.method = method

    def forward(self, *args: Tensor) -> Tensor:
        return self.method(*args)


class FlowStep(nn.Module):
    """The step's flow branch as one module (nodes /flow/encode/..., /flow/match/...): the new frame's features
    [1,C,Hf,Wf], the previous frame's phi [1,C/2,Hm,Wm], poses [1,T,3] -> the new phi, the newest pair's flow."""

    def __init__(self, model: RaFD) -> None:
        super().__init__()
        self.encode = Method(model.flow_features)  # phi once per frame; the previous one is cached
        self.match = Method(model.pair_flow_encoded)

    def forward(self, features: Tensor, past_flow_features: Tensor, poses: Tensor) -> tuple[Tensor, Tensor]:
        flow_features = self.encode(features)
        relative = relative_pose_torch(poses[:, -2], poses[:, -1])
        return flow_features, self.match(past_flow_features, flow_features, relative)


class StepGraph(nn.Module):
    """One new frame + the previous window's caches -> detections of the new window, its flows, the new features.

    inputs:  frame [1,1,S,S], poses [1,T,3], past_features [1,T-1,C,Hf,Wf], past_flows [1,T-2,2,Hf,Wf] (T = 4),
             past_flow_features [1,C/2,Hm,Wm] (phi of the previous frame, computed by the previous step)
    outputs: heatmap, scores, boxes, flow [1,T-1,2,Hf,Wf], features [1,C,Hf,Wf], flow_features [1,C/2,Hm,Wm]
    For T = 1 it is the single-frame model: inputs frame, poses [1,1,3]; outputs heatmap, scores, boxes.
    """

    def __init__(self, model: RaFD, num_frames: int) -> None:
        super().__init__()
        self.model = model
        self.num_frames = num_frames
        self.flow = FlowStep(model) if num_frames > 1 else None

    def forward(self, frame: Tensor, poses: Tensor, *caches: Tensor) -> tuple[Tensor, ...]:
        if self.num_frames == 1:
            out = self.model(frame[:, None], poses)
            return out["heatmap"], out["scores"], out["boxes"]
        # caches in contract order: past_features, [past_flows (T = 4)], past_flow_features
        past_features, past_flow_features = caches[0], caches[-1]
        past_flows = caches[1] if self.num_frames > 2 else None
        features = self.model.encode_frame(frame)
        assert self.flow is not None  # built for num_frames > 1
        flow_features, flow = self.flow(features, past_flow_features, poses)
        flows = flow[:, None] if past_flows is None else torch.cat([past_flows, flow[:, None]], 1)
        out = self.model.detect_newest(past_features, features, flows, poses)
        return out["heatmap"], out["scores"], out["boxes"], flows, features, flow_features


class WindowGraph(nn.Module):
    """model.forward on a full window: frames [1,T,1,S,S], poses [1,T,3] -> heatmap, scores, boxes(, flow)."""

    def __init__(self, model: RaFD, num_frames: int) -> None:
        super().__init__()
        self.model = model
        self.num_frames = num_frames

    def forward(self, frames: Tensor, poses: Tensor) -> tuple[Tensor, ...]:
        out = self.model(frames, poses)
        if self.num_frames == 1:
            return out["heatmap"], out["scores"], out["boxes"]
        return out["heatmap"], out["scores"], out["boxes"], out["flow"]


@torch.no_grad()
def feature_channels(model: RaFD, cfg: RaFDConfig) -> int:
    """C of model.encode_frame (the step graph's cached feature maps)."""
    return int(model.encode_frame(torch.zeros(1, 1, cfg.input_size, cfg.input_size)).shape[1])


def build_graph(model: RaFD, cfg: RaFDConfig, form: str) -> nn.Module:
    if form not in FORMS:
        raise ValueError(f"form must be one of {FORMS}, got {form!r}")
    return (StepGraph if form == "step" else WindowGraph)(model, cfg.num_frames).eval()


def example_inputs(cfg: RaFDConfig, form: str, channels: int, seed: int = 0) -> tuple[Tensor, ...]:
    """Random inputs of the graph's static shapes (frames in [0, 1], small ego motion), in contract order."""
    generator = torch.Generator().manual_seed(seed)
    T, S, F = cfg.num_frames, cfg.input_size, cfg.feature_size
    poses = torch.cumsum(torch.randn(1, T, 3, generator=generator) * torch.tensor([1.0, 1.0, 0.05]), 1)
    if form == "window":
        return torch.rand(1, T, 1, S, S, generator=generator), poses
    inputs: tuple[Tensor, ...] = (torch.rand(1, 1, S, S, generator=generator), poses)
    if T > 1:
        inputs += (torch.randn(1, T - 1, channels, F, F, generator=generator),)
    if T > 2:
        inputs += (torch.randn(1, T - 2, 2, F, F, generator=generator),)
    if T > 1:  # past_flow_features: phi of the previous frame, cfg.flow_channels on the flow grid
        inputs += (torch.randn(1, cfg.flow_channels, cfg.flow_size, cfg.flow_size, generator=generator),)
    return inputs
