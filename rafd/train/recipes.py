"""Named training recipes: a network config, the optimisation settings and whether to augment, in one name.

`rafd-train --config NAME` starts from the recipe; any flag given on the command line overrides its field, and the
checkpoint records the recipe's name and every resulting setting (rafd.train.trainer.Trainer.save).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from rafd.config import InputConfig, RaFDConfig
from rafd.data.augment import AugmentConfig
from rafd.train.trainer import TrainConfig


@dataclass(frozen=True)
class Recipe:
    name: str
    description: str
    model: RaFDConfig
    train: TrainConfig
    augment: AugmentConfig | None  # rafd.data.augment (None: no augmentation)


def shipped_model_config() -> RaFDConfig:
    """The `default` recipe's network: the tiny config at the protocol's 256 px crop, with the speed options
    (flow branch at stride 8, 16-cell attention windows: neither is the paper's), the gain-robust input, and pre-norm
    propagation blocks that start as the identity (so a single-frame model's weights start a multi-frame run).
    The shipped default model was this network until 2026-12-02 (76e6099a); it is now cpu_model_config()'s, built on
    this one (README: "The shipped default model")."""
    tiny = RaFDConfig.tiny(input_size=256)
    return tiny.replace(
        input=InputConfig(normalisation="local_contrast", window=47),
        flow=dataclasses.replace(tiny.flow, stride=8),
        enhance=dataclasses.replace(tiny.enhance, window=16),
        propagation=dataclasses.replace(tiny.propagation, norm="pre"),
    )


def cpu_model_config() -> RaFDConfig:
    """The `cpu` recipe's network: the default network reshaped for a CPU's few large operations (docs/model.md,
    "The CPU network"): residual dilated-convolution enhancement in place of window attention, a local cost volume
    (radius 3 flow cells at stride 8: motions up to 4.2 m per frame, 16.7 m/s at 4 Hz, relative to the static world)
    without the cross-attention blocks, and one joint propagation block that samples all past frames at once, one
    point per frame, with a narrow FFN (1 and 1x: 0.19 of the default's step against 0.21 with 2 points and 2x, side
    by side, random weights, docs/model.md); the input, backbone, neck and head are the default's."""
    base = shipped_model_config()
    return base.replace(
        enhance=dataclasses.replace(base.enhance, kind="conv", window=0),
        flow=dataclasses.replace(base.flow, num_cross_blocks=0, local_radius=3, channels=8),
        propagation=dataclasses.replace(base.propagation, mode="joint", num_blocks=1, num_points=1, ffn_ratio=1),
    )


RECIPES: dict[str, Recipe] = {
    recipe.name: recipe
    for recipe in (
        Recipe(
            "paper",
            "the paper's setting (section 3): ResNet-34 RaFD, 256 px crop, 4 frames; Adam, lr 2e-4, weight decay 1e-2, "
            "global batch 8, 10 epochs; no augmentation, no learning-rate schedule (the paper states none)",
            RaFDConfig.paper(),
            TrainConfig(epochs=10, batch_size=8, lr=2e-4, weight_decay=1e-2, optimizer="adam", lr_schedule="constant"),
            augment=None,
        ),
        Recipe(
            "tiny",
            "every part of RaFD small enough for a CPU (128 px crop, 4 frames); AdamW, lr 1e-3, weight decay 1e-2, "
            "batch 4, 8 epochs, flip + rotation augmentation (the synthetic benchmark's setting)",
            RaFDConfig.tiny(),
            TrainConfig(epochs=8, batch_size=4, lr=1e-3, weight_decay=1e-2, optimizer="adamw", lr_schedule="constant"),
            augment=AugmentConfig(),
        ),
        Recipe(
            "default",
            "the shipped model's network: tiny RaFD at 256 px, 4 frames, flow at stride 8, 16-cell attention "
            "windows, gain-robust input, pre-norm propagation; AdamW 1e-3 with "
            "cosine decay, batch 4, 6 epochs, bf16-friendly; flip + rotation, radar intensity changes and crops up to "
            "65 m from the radar (full-scan tiles)",
            shipped_model_config(),
            TrainConfig(epochs=6, batch_size=4, lr=1e-3, weight_decay=1e-2, optimizer="adamw", lr_schedule="cosine"),
            augment=AugmentConfig(intensity_probability=0.8, shift_probability=0.6, shift_max_m=65.0),
        ),
        Recipe(
            "cpu",
            "the default recipe's training with the network reshaped for a CPU: convolutional enhancement, a local "
            "cost volume without cross-attention, one joint propagation block over all past frames",
            cpu_model_config(),
            TrainConfig(epochs=6, batch_size=4, lr=1e-3, weight_decay=1e-2, optimizer="adamw", lr_schedule="cosine"),
            augment=AugmentConfig(intensity_probability=0.8, shift_probability=0.6, shift_max_m=65.0),
        ),
    )
}
