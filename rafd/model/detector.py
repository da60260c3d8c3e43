"""RaFD: the whole network, decomposed into the streaming steps encode_frame / pair_flow / detect."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from rafd.model.align import relative_pose_torch
from rafd.model.flow import FlowEstimator
from rafd.model.head import DetectionHead
from rafd.model.joint_propagation import JointPropagation
from rafd.model.propagation import FlowGuidedPropagation


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

    Each frame's features and each consecutive pair's flow depend only on those frames, so a stream
    caches them; forward is exactly encode_frame on every frame, pair_flow on every pair, then detect,
    so a streaming run equals the window run by construction. For T = 1 there is no flow branch and no
    propagation (single-frame CenterFormer baseline).
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

    def flow_features(self, features: Tensor) -> Tensor:
        """S [B, C, Hf, Wf] -> E = phi(S) [B, C/2, Hm, Wm]: per frame, so a stream caches it beside S."""
        if self.flow is None:
            raise RuntimeError("a single-frame RaFD has no flow branch")
        return self.flow.encode(features)

    def pair_flow_encoded(self, encoded_prev: Tensor, encoded_cur: Tensor, relative_pose: Tensor) -> Tensor:
        """pair_flow from cached E_prev, E_cur [B, C/2, Hm, Wm] (flow_features): equal to pair_flow in eval mode
        (phi's BN uses its running statistics there, so phi of a frame does not depend on its pair)."""
        if self.flow is None:
            raise RuntimeError("a single-frame RaFD has no flow branch")
        return self.flow.match(encoded_prev, encoded_cur, relative_pose.to(encoded_cur.dtype))

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
