"""RaFD: the whole network, and its streaming step (`step`: one new frame and the cache of the previous ones)."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor, nn

from rafd.model.align import relative_pose_torch
from rafd.model.flow import FlowEstimator
from rafd.model.head import DetectionHead
from rafd.model.joint_propagation import JointPropagation
from rafd.model.propagation import FlowGuidedPropagation


class Stage(nn.Module):
    """A method of another module called as a module of its own, so that the ONNX exporter names the step graph's
    nodes after it (/flow_encode/..., /flow_match/...: units of a by-module profile and of the float32 islands). It
    holds no parameters: the method's module keeps them, so the state dict is unchanged."""

    def __init__(self, method: Callable[..., Tensor]) -> None:
        super().__init__()
        self.method = method

    def forward(self, *args: Tensor) -> Tensor:
        return self.method(*args)


class FrameEncoder(nn.Module):
    """Input normalisation + backbone + neck + enhancement: frame [B, 1, S, S] -> S features [B, C, Hf, Wf]."""

    def __init__(self, normalise: nn.Module, backbone: nn.Module, neck: nn.Module, enhancement: nn.Module) -> None:
        super().__init__()
        self.normalise = normalise  # rafd.model.normalise (identity for the paper's grey / 255)
        self.backbone = backbone
        self.neck = neck
        self.enhancement = enhancement

    def forward(self, frame: Tensor) -> Tensor:
        return self.enhancement(self.neck(self.backbone(self.normalise(frame))))


class RaFD(nn.Module):
    """frames [B, T, 1, S, S] in [0, 1] + world poses [B, T, 3] -> detections in the newest ego frame.

    forward is encode_frame on every frame, pair_flow on every consecutive pair, then detect. Each frame's
    features and each pair's flow depend only on those frames, so a stream caches them: `step` takes one new
    frame and the cache (which the runtime carries without knowing what it holds) and equals forward on the
    stream's newest window. For T = 1 there is no flow branch and no propagation (single-frame CenterFormer
    baseline).
    """

    def __init__(
        self,
        encoder: FrameEncoder,
        flow: FlowEstimator | None,
        propagation: FlowGuidedPropagation | JointPropagation | None,
        head: DetectionHead,
        num_frames: int,
    ) -> None:
        super().__init__()
        if (num_frames > 1) != (flow is not None and propagation is not None):
            raise ValueError("flow and propagation are needed exactly when num_frames > 1")
        self.encoder = encoder
        self.flow = flow
        self.propagation = propagation
        self.head = head
        self.num_frames = num_frames
        if flow is not None:  # the step's two flow stages: phi once per frame (cached), matching once per pair
            self.flow_encode = Stage(flow.encode)
            self.flow_match = Stage(flow.match)

    def encode_frame(self, frame: Tensor) -> Tensor:
        """[B, 1, S, S] -> [B, C, Hf, Wf]."""
        return self.encoder(frame)

    def pair_flow(self, features_prev: Tensor, features_cur: Tensor, relative_pose: Tensor) -> Tensor:
        """S_prev, S_cur [B, C, Hf, Wf], relative_pose [B, 3] -> flow [B, 2, Hf, Wf] metres on the current grid.

        relative_pose must be relative_pose_torch(pose_prev, pose_cur) (= geometry.relative_pose(prev, cur)),
        the transform taking previous-frame points into the current frame: p_cur = R(yaw) p_prev + (x, y).
        """
        if self.flow is None:
            raise RuntimeError("a single-frame RaFD has no flow branch")
        return self.flow(features_prev, features_cur, relative_pose.to(features_cur.dtype))

    def detect(
        self,
        features: Tensor,
        flows: Tensor | None,
        poses: Tensor,
        gt_indices: Tensor | None = None,
        gt_mask: Tensor | None = None,
    ) -> dict[str, Tensor]:
        """features [B, T, C, Hf, Wf], flows [B, T-1, 2, Hf, Wf] (None for T = 1), poses [B, T, 3] -> outputs."""
        num_frames = features.shape[1]
        if num_frames != self.num_frames:
            raise ValueError(f"model expects {self.num_frames} frames, got {num_frames}")
        propagated = features[:, 0]  # T = 1: S_1
        if num_frames > 1:
            if flows is None or self.propagation is None:
                raise ValueError("multi-frame detect needs the pair flows")
            propagated = self.propagation.propagate(features, flows, poses)  # [B, C, Hf, Wf]
        return self.head(propagated, gt_indices, gt_mask)

    def detect_newest(self, past_features: Tensor, features: Tensor, flows: Tensor, poses: Tensor) -> dict[str, Tensor]:
        """detect for a stream's step: past_features [B, T-1, C, Hf, Wf] (cached), the newest features [B, C, Hf, Wf].
        The joint propagation reads the two apart, so the window is never copied into one tensor."""
        if isinstance(self.propagation, JointPropagation):
            return self.head(self.propagation(past_features, features, flows, poses))
        return self.detect(torch.cat([past_features, features[:, None]], 1), flows, poses)

    @torch.no_grad()
    def empty_cache(self, batch: int, input_size: int) -> dict[str, Tensor]:
        """The cache `step` takes on a stream's first frame: zeros, `frames` 0 (nothing seen). Its names and shapes
        are the step graph's cache inputs; what they hold is the model's business (see `step`)."""
        T = self.num_frames
        if T == 1:
            return {}
        if self.training:  # the shapes come from a forward pass, which would move BatchNorm's statistics
            raise RuntimeError("empty_cache is for streaming: call model.eval() first")
        device = next(self.parameters()).device
        features = self.encode_frame(torch.zeros(1, 1, input_size, input_size, device=device))  # [1, C, Hf, Wf]
        encoded = self.flow_encode(features)  # [1, Cm, Hm, Wm]
        shapes = {
            "features": (T - 1, *features.shape[1:]),  # the last T-1 frames' S, oldest first
            "flow_features": tuple(encoded.shape[1:]),  # the last frame's E = phi(S)
            "poses": (T - 1, 3),  # the last T-1 frames' poses in the last frame's ego frame
            "frames": (),  # real frames in the last window (0: a new stream)
        }
        if T > 2:
            shapes["flows"] = (T - 2, 2, *features.shape[2:])  # the last T-2 pair flows, oldest first
        return {name: torch.zeros(batch, *shape, device=device) for name, shape in shapes.items()}

    def step(
        self, frame: Tensor, pose: Tensor, cache: dict[str, Tensor]
    ) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
        """One new frame of a stream: frame [B, 1, S, S], pose [B, 3] (this frame's pose in the previous frame's ego
        frame, geometry.relative_pose(current, previous); anything on a stream's first frame), the cache of the
        previous step (empty_cache's on the first) -> (outputs for the window ending at this frame, the new cache).

        outputs: heatmap, scores, boxes as forward's, flow [B, 2, Hf, Wf] (the newest pair's; T > 1), frames_used
        [B] (real frames in the window). Exactly forward on the window padded by the warm-up rule (a window of fewer
        than T real frames repeats its oldest frame with its pose): each frame's S and E and each pair's flow depend
        only on those frames, so the cache keeps them and a step computes one frame's and one pair's. On a stream's
        first frame (cache frames 0) the padding is this frame itself: the past features are its own, the pair flows
        its self-pair flow, the poses its own.
        """
        features = self.encode_frame(frame)  # [B, C, Hf, Wf]
        T = self.num_frames
        if T == 1:
            return {**self.head(features), "frames_used": torch.ones_like(frame[:, 0, 0, 0])}, {}
        seen = cache["frames"]  # [B]
        started = seen > 0  # [B]

        def continued(cached: Tensor, fresh: Tensor) -> Tensor:
            """The cache where the stream has started, else this frame's own `fresh` padding (broadcast over the
            cache's frames: never materialised)."""
            return torch.where(started.reshape(-1, *[1] * (cached.dim() - 1)), cached, fresh)

        past = continued(cache["features"], features[:, None])  # [B, T-1, C, Hf, Wf]
        encoded = self.flow_encode(features)  # [B, Cm, Hm, Wm]
        past_encoded = continued(cache["flow_features"], encoded)  # [B, Cm, Hm, Wm]
        # the window's poses in this frame's ego frame (this frame's is the origin): the past ones moved by `pose`
        here = torch.zeros_like(pose)[:, None]  # [B, 1, 3]
        moved = relative_pose_torch(cache["poses"], pose[:, None])  # [B, T-1, 3]
        poses = torch.cat([continued(moved, here), here], 1)  # [B, T, 3]
        newest = self.flow_match(
            past_encoded, encoded, relative_pose_torch(poses[:, -2], poses[:, -1])
        )  # [B, 2, Hf, Wf]
        flows = newest[:, None]  # [B, 1, 2, Hf, Wf]
        if T > 2:
            flows = torch.cat([continued(cache["flows"], flows), flows], 1)  # [B, T-1, 2, Hf, Wf]
        outputs = self.detect_newest(past, features, flows, poses)
        frames_used = torch.clamp(seen + 1, max=T)  # [B]
        new_cache = {
            "features": torch.cat([past[:, 1:], features[:, None]], 1),
            "flow_features": encoded,
            "poses": poses[:, 1:],
            # the same count as frames_used, computed apart: one value cannot be two graph outputs
            "frames": torch.clamp(seen + 1, max=T),
        }
        if T > 2:
            new_cache["flows"] = flows[:, 1:]
        return {**outputs, "flow": newest, "frames_used": frames_used}, new_cache

    def forward(
        self, frames: Tensor, poses: Tensor, gt_indices: Tensor | None = None, gt_mask: Tensor | None = None
    ) -> dict[str, Tensor]:
        batch, num_frames = frames.shape[:2]
        # all frames through the encoder as one batch: [B*T, 1, S, S] -> [B*T, C, Hf, Wf]
        encoded = self.encode_frame(frames.reshape(batch * num_frames, *frames.shape[2:]))
        features = encoded.reshape(batch, num_frames, *encoded.shape[1:])  # [B, T, C, Hf, Wf]
        flows = None
        if num_frames > 1:
            relative = relative_pose_torch(poses[:, :-1], poses[:, 1:])  # [B, T-1, 3]
            pairs = batch * (num_frames - 1)
            # every consecutive pair as one batch: [B*(T-1), C, Hf, Wf] each
            flat = self.pair_flow(
                features[:, :-1].reshape(pairs, *features.shape[2:]),
                features[:, 1:].reshape(pairs, *features.shape[2:]),
                relative.reshape(pairs, 3),
            )  # [B*(T-1), 2, Hf, Wf]
            flows = flat.reshape(batch, num_frames - 1, *flat.shape[1:])  # [B, T-1, 2, Hf, Wf]
        outputs = self.detect(features, flows, poses, gt_indices, gt_mask)
        if flows is not None:
            outputs["flow"] = flows
        return outputs
