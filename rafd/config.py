"""Typed configuration of the RaFD network (torch-free: the service reads it from ONNX metadata)."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from typing import Any

from rafd.config_tree import from_dict
from rafd.geometry import RADIATE_RESOLUTION

ALLOWED_FRAMES = (1, 2, 4)
BOX_ENCODINGS = ("symmetric", "as_labelled")
ENHANCE_KINDS = ("window_attention", "conv")
PROPAGATION_MODES = ("chain", "joint")
FREEZABLE = ("encoder", "flow", "propagation", "head")  # RaFD's top-level parts, for rafd-train --freeze
# What two networks must share for one's weights (rafd train --init) or heatmap (--teacher) to mean the same to the
# other: the pixels they read and the cells and classes they predict; width, depth and frame count may differ.
SAME_INPUT_AND_TARGETS = ("input_size", "resolution", "output_stride", "input", "class_names", "targets")


@dataclass(frozen=True)
class InputConfig:
    # The network's first module (rafd.model.normalise): "none" = grey / 255 as the paper; "local_contrast" = log grey
    # standardised over a window x window pixel box, robust to the receiver's gain, gamma and range-dependent floor.
    normalisation: str = "none"
    window: int = 47  # pixels (8.2 m at RADIATE's resolution), odd

    def __post_init__(self) -> None:
        if self.normalisation not in ("none", "local_contrast"):
            raise ValueError(f"input.normalisation must be 'none' or 'local_contrast', got {self.normalisation!r}")
        if self.window < 3 or self.window % 2 == 0:
            raise ValueError(f"input.window must be an odd number of pixels >= 3, got {self.window}")


@dataclass(frozen=True)
class BackboneConfig:
    # Basic-block ResNet: blocks per stage. (3, 4, 6, 3) is ResNet-34 as in the paper.
    blocks: tuple[int, ...] = (3, 4, 6, 3)
    # Channels per stage; the stem has channels[0].
    channels: tuple[int, ...] = (64, 128, 256, 512)


@dataclass(frozen=True)
class NeckConfig:
    # FPN-style top-down neck fused at stride `output_stride` into one BEV map of `channels`.
    channels: int = 128


@dataclass(frozen=True)
class EnhanceConfig:
    # Feature enhancement: blocks of (regular window, shifted window) single-head attention.
    enabled: bool = True  # False = the "without enhancement" ablation
    num_blocks: int = 2
    ffn_ratio: int = 2
    # Speed option (changes the mathematics): attention window side in cells; 0 = Hf/2 x Wf/2 (the paper's
    # 2 x 2 windows). A smaller window (e.g. 16 cells at 64 x 64) cuts the quadratic attention cost;
    # the shifted layer shifts by half a window. Must divide the feature map side and be even.
    window: int = 0
    # "window_attention": the paper's Swin-style blocks; "conv": residual blocks of two 3x3 convolutions (the second
    # dilated by 2 for context), a few large operations in place of the attention's many small ones (the CPU recipe).
    kind: str = "window_attention"

    def __post_init__(self) -> None:
        if self.kind not in ENHANCE_KINDS:
            raise ValueError(f"enhance.kind must be one of {ENHANCE_KINDS}, got {self.kind!r}")


@dataclass(frozen=True)
class FlowConfig:
    # Flow estimation: global single-head cross-attention blocks between aligned pair features.
    num_cross_blocks: int = 2
    ffn_ratio: int = 2
    # Speed option (changes the mathematics): input pixels per flow cell. 4 = output_stride (the paper);
    # 8 runs phi, alignment, cross-attention and the cost volume on a 2x average-pooled map (4x fewer
    # cells, 16x smaller cost volume) and upsamples the flow (metres) bilinearly to the detection grid.
    stride: int = 4
    # Matching: 0 = the paper's global correlation (softmax over every previous cell); r > 0 = a local cost volume
    # over the (2r + 1)^2 previous cells around each cell (a bounded displacement: r flow cells per frame), so no cell
    # can match far away content, and the cost volume is Hm*Wm*(2r+1)^2 instead of (Hm*Wm)^2.
    local_radius: int = 0
    # Channels of the flow features E = phi(S) that are matched; 0 = C/2 (the paper). The cost volume's cost is per
    # channel, so the CPU recipe matches on fewer.
    channels: int = 0


@dataclass(frozen=True)
class PropagationConfig:
    # Flow-guided deformable attention blocks chained oldest -> newest.
    num_blocks: int = 2
    num_points: int = 4  # sampling points per query and frame
    # False = vanilla deformable attention (reference r_t, no flow): the paper's ablation baseline.
    flow_guided: bool = True
    ffn_ratio: int = 2
    # "post": Deformable DETR's post-norm blocks (every propagated cell normalised); "pre": pre-norm residual blocks
    # that start as the identity (rafd.model.deformable.DeformableLayer), so the newest frame's features reach the
    # head unchanged until the propagation learns what the past adds.
    norm: str = "post"
    # "chain": the paper's, T_t = blocks(S_t, T_{t-1}) oldest -> newest ((T-1) x num_blocks blocks per window);
    # "joint": the newest frame's cells read every past frame's features in ONE deformable sampling (values: the
    # cached past S maps; references: the cell moved back by age x the newest flow, constant velocity, then through
    # the ego motion into that frame), num_blocks blocks per window whatever T.
    mode: str = "chain"

    def __post_init__(self) -> None:
        if self.norm not in ("post", "pre"):
            raise ValueError(f"propagation.norm must be 'post' or 'pre', got {self.norm!r}")
        if self.mode not in PROPAGATION_MODES:
            raise ValueError(f"propagation.mode must be one of {PROPAGATION_MODES}, got {self.mode!r}")


@dataclass(frozen=True)
class HeadConfig:
    num_queries: int = 64  # K: fixed number of top-K heatmap peaks -> queries (static for ONNX)
    decoder_layers: int = 2
    num_points: int = 4  # deformable cross-attention sampling points per query
    ffn_ratio: int = 2
    num_classes: int = 1  # one merged `vehicle` class (benchmark protocol)
    # How orientation and size are regressed. "symmetric": a box is the same box turned by 180 degrees, and RADIATE's
    # annotators flip yaw by 180 degrees and swap width/length within one track, so the targets are the canonical
    # box (width <= length) with (sin 2yaw, cos 2yaw); decoding returns width <= length, yaw in [-pi/2, pi/2).
    # "as_labelled": (sin yaw, cos yaw) and log(width, length) exactly as annotated (the targets before "symmetric").
    box_encoding: str = "symmetric"

    def __post_init__(self) -> None:
        if self.box_encoding not in BOX_ENCODINGS:
            raise ValueError(f"box_encoding must be one of {BOX_ENCODINGS}, got {self.box_encoding!r}")


@dataclass(frozen=True)
class TargetConfig:
    # Training targets (kept in the config so a checkpoint records how it was trained).
    # Heatmap Gaussian radius = max(heatmap_min_radius, int(gaussian_radius(l, w, heatmap_min_overlap))) in cells:
    # CenterPoint / CenterFormer use overlap 0.1 and a floor of 2 (overlap 0.7 and floor 1 give every car 1 cell).
    heatmap_min_overlap: float = 0.1
    heatmap_min_radius: int = 2
    # Pseudo-GT flow region radius max(f(hw), flow_min_radius) with f = gaussian_radius(l, w, flow_min_overlap).
    flow_min_overlap: float = 0.7
    flow_min_radius: float = 2.0  # gamma, cells


@dataclass(frozen=True)
class RaFDConfig:
    input_size: int = 256  # square centre crop of the radar scan, pixels
    num_frames: int = 4  # 1 (single-frame baseline), 2 or 4
    output_stride: int = 4  # feature map is input_size / output_stride (TempoRadar: 256 -> 64)
    resolution: float = RADIATE_RESOLUTION  # metres per input pixel (RADIATE Navtech)
    class_names: tuple[str, ...] = ("vehicle",)
    input: InputConfig = field(default_factory=InputConfig)
    backbone: BackboneConfig = field(default_factory=BackboneConfig)
    neck: NeckConfig = field(default_factory=NeckConfig)
    enhance: EnhanceConfig = field(default_factory=EnhanceConfig)
    flow: FlowConfig = field(default_factory=FlowConfig)
    propagation: PropagationConfig = field(default_factory=PropagationConfig)
    head: HeadConfig = field(default_factory=HeadConfig)
    targets: TargetConfig = field(default_factory=TargetConfig)

    def __post_init__(self) -> None:
        if self.num_frames not in ALLOWED_FRAMES:
            raise ValueError(f"num_frames must be one of {ALLOWED_FRAMES}, got {self.num_frames}")
        if self.input_size % (2 * self.output_stride):
            raise ValueError("input_size must be divisible by 2 * output_stride (two attention windows per side)")
        if len(self.backbone.blocks) != len(self.backbone.channels):
            raise ValueError("backbone.blocks and backbone.channels must have the same length")
        # flow.stride / enhance.window: the speed options
        if self.flow.stride % self.output_stride or self.input_size % self.flow.stride:
            raise ValueError(
                f"flow.stride {self.flow.stride} must be a multiple of output_stride "
                f"{self.output_stride} and divide input_size {self.input_size}"
            )
        if self.flow.local_radius < 0 or self.flow.local_radius >= self.flow_size // 2:
            raise ValueError(f"flow.local_radius {self.flow.local_radius} must be in [0, {self.flow_size // 2})")
        window = self.enhance.window
        if window and (window < 2 or window % 2 or self.feature_size % window):
            raise ValueError(
                f"enhance.window {window} must be even and divide the feature map side "
                f"{self.feature_size} (0 = half the side, the paper)"
            )

    @property
    def feature_size(self) -> int:
        """Side of the BEV feature map, Hf = Wf."""
        return self.input_size // self.output_stride

    @property
    def cell_size(self) -> float:
        """Metres per feature cell."""
        return self.resolution * self.output_stride

    @property
    def flow_size(self) -> int:
        """Side of the map the flow is matched on (= feature_size unless flow.stride is coarser)."""
        return self.input_size // self.flow.stride

    @property
    def flow_channels(self) -> int:
        """Channels of the flow features E = phi(S) (flow.channels, 0 = half the neck's)."""
        return self.flow.channels or self.neck.channels // 2

    @property
    def enhance_window(self) -> int:
        """Side of the enhancement attention windows in cells (enhance.window, 0 = half the map)."""
        return self.enhance.window or self.feature_size // 2

    @classmethod
    def paper(cls) -> RaFDConfig:
        """The paper's setting: ResNet-34 + FPN neck, stride 4, 256x256, 4 frames."""
        return cls()

    @classmethod
    def tiny(cls, **overrides: Any) -> RaFDConfig:
        """Every part of the architecture, small enough to train on a CPU (128x128, 4 frames)."""
        base = cls(
            input_size=128,
            num_frames=4,
            output_stride=4,
            backbone=BackboneConfig(blocks=(1, 1, 1), channels=(16, 32, 64)),
            neck=NeckConfig(channels=32),
            head=HeadConfig(num_queries=32, decoder_layers=1, num_points=4),
        )
        return base.replace(**overrides) if overrides else base

    def replace(self, **changes: Any) -> RaFDConfig:
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> RaFDConfig:
        """Rebuild from `to_dict()`; an unknown or a missing key is an error: a stored config names every field, so a
        field it lacks never silently takes today's default."""
        return from_dict(cls, data)

    @classmethod
    def from_json(cls, text: str) -> RaFDConfig:
        return cls.from_dict(json.loads(text))
