"""build_model(cfg): the only place that reads RaFDConfig and wires the modules together."""

from __future__ import annotations

from torch import nn

from rafd.config import RaFDConfig
from rafd.model.align import cell_centres, metres_to_grid
from rafd.model.attention import AttentionLayer
from rafd.model.backbone import ResNet
from rafd.model.decoder import BoxRegression, DecoderLayer, QueryDecoder
from rafd.model.deformable import DeformableAttention, DeformableLayer
from rafd.model.detector import FrameEncoder, RaFD
from rafd.model.enhance import build_enhancement
from rafd.model.flow import FlowEstimator, build_flow_encoder
from rafd.model.head import DetectionHead, HeatmapHead
from rafd.model.joint_propagation import JointDeformableAttention, JointPropagation
from rafd.model.neck import FPNNeck
from rafd.model.normalise import build_normalisation
from rafd.model.position import sine_position_encoding
from rafd.model.propagation import FlowGuidedPropagation


def build_model(cfg: RaFDConfig) -> RaFD:
    """RaFDConfig -> RaFD (train mode, fresh weights); static buffers sized for cfg.input_size."""
    if cfg.output_stride != 4:
        raise ValueError(f"output_stride must be 4 (the first ResNet stage's stride), got {cfg.output_stride}")
    channels = cfg.neck.channels
    if channels % 2:
        raise ValueError(f"neck.channels must be even (flow features have C/2), got {channels}")
    size = cfg.feature_size
    window = cfg.enhance_window
    if window % 2 or size % window:
        raise ValueError(f"feature map side {size} must be a multiple of the even enhancement window {window}")
    centres = cell_centres(size, cfg.input_size, cfg.resolution)  # [Hf*Wf, 2] metres
    half_extent = cfg.input_size * cfg.resolution / 2.0  # metres from the radar to the map's edge
    grid = metres_to_grid(centres, half_extent)  # [Hf*Wf, 2] normalised

    backbone = ResNet(cfg.backbone.blocks, cfg.backbone.channels)
    encoder = FrameEncoder(
        build_normalisation(cfg.input.normalisation, cfg.input.window),
        backbone,
        FPNNeck(backbone.out_channels, channels),
        build_enhancement(
            channels,
            size,
            cfg.enhance.num_blocks,
            cfg.enhance.ffn_ratio,
            cfg.enhance.enabled,
            window,
            cfg.enhance.kind,
        ),
    )

    flow: FlowEstimator | None = None
    propagation: FlowGuidedPropagation | JointPropagation | None = None
    if cfg.num_frames > 1:
        half, flow_size = cfg.flow_channels, cfg.flow_size  # flow.stride: matching grid Hm = Wm = flow_size
        flow = FlowEstimator(
            build_flow_encoder(channels, half),
            [AttentionLayer(half, cfg.flow.ffn_ratio) for _ in range(cfg.flow.num_cross_blocks)],
            sine_position_encoding(half, flow_size, flow_size),
            cell_centres(flow_size, cfg.input_size, cfg.resolution),
            half_extent,
            pool=cfg.flow.stride // cfg.output_stride,
            local_radius=cfg.flow.local_radius,
        )
        prop_cfg = cfg.propagation
        joint = prop_cfg.mode == "joint"

        def sampling() -> DeformableAttention:
            if joint:  # every past frame in one sampling, values read in C/2 channels
                past = cfg.num_frames - 1
                return JointDeformableAttention(channels, past, prop_cfg.num_points, (size, size), channels // 2)
            return DeformableAttention(channels, prop_cfg.num_points, (size, size))

        layers = [
            DeformableLayer(sampling(), channels, prop_cfg.ffn_ratio, norm=prop_cfg.norm)
            for _ in range(prop_cfg.num_blocks)
        ]
        if joint:
            propagation = JointPropagation(layers, centres.clone(), half_extent, prop_cfg.flow_guided, cfg.num_frames)
        else:
            propagation = FlowGuidedPropagation(layers, centres.clone(), half_extent, prop_cfg.flow_guided)

    head_cfg = cfg.head
    if head_cfg.num_queries > size * size:
        raise ValueError(f"num_queries {head_cfg.num_queries} exceeds the {size * size} cells")
    decoder = QueryDecoder(
        [
            DecoderLayer(
                AttentionLayer(channels, ffn_ratio=0),
                DeformableLayer(
                    DeformableAttention(channels, head_cfg.num_points, (size, size)), channels, head_cfg.ffn_ratio
                ),
            )
            for _ in range(head_cfg.decoder_layers)
        ]
    )
    head = DetectionHead(
        HeatmapHead(channels, head_cfg.num_classes),
        nn.Linear(2, channels),
        decoder,
        BoxRegression(channels),
        head_cfg.num_queries,
        centres.clone(),
        grid.clone(),
        cfg.cell_size,
        head_cfg.box_encoding,
    )
    return RaFD(encoder, flow, propagation, head, cfg.num_frames)


def count_parameters(model: nn.Module) -> int:
    """Number of learned parameters."""
    return sum(p.numel() for p in model.parameters())
