"""Named training recipes: each a list of dotted settings of the run config (rafd.train.config), applied on top of
the recipe it builds on, so a recipe says only how it differs.

`rafd train ROOT --config NAME [KEY=VALUE ...]` starts from the recipe and applies the command line's settings after
it; the checkpoint records the recipe's name and the whole resulting config.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import cache

from rafd.config import RaFDConfig
from rafd.config_tree import parse_overrides
from rafd.train.config import RunConfig


@dataclass(frozen=True)
class Recipe:
    name: str
    description: str
    settings: tuple[str, ...]  # KEY=VALUE, applied in order
    base: str | None = None  # the recipe this one builds on; None: RunConfig's defaults (the paper's)


# The tiny network (RaFDConfig.tiny: every part of the architecture, small enough to train on a CPU).
TINY_NETWORK = (
    "model.input_size=128",
    "model.backbone.blocks=1,1,1",
    "model.backbone.channels=16,32,64",
    "model.neck.channels=32",
    "model.head.num_queries=32",
    "model.head.decoder_layers=1",
)

RECIPES: dict[str, Recipe] = {
    recipe.name: recipe
    for recipe in (
        Recipe(
            "paper",
            "the paper's setting (section 3): ResNet-34 RaFD, 256 px crop, 4 frames; Adam, lr 2e-4, weight decay 1e-2, "
            "global batch 8, 10 epochs; no augmentation, no learning-rate schedule (the paper states none)",
            (),
        ),
        Recipe(
            "tiny",
            "every part of RaFD small enough for a CPU (128 px crop, 4 frames); AdamW, lr 1e-3, weight decay 1e-2, "
            "batch 4, 8 epochs, flip + rotation augmentation (the synthetic benchmark's setting)",
            (
                *TINY_NETWORK,
                "train.epochs=8",
                "train.batch_size=4",
                "train.lr=1e-3",
                "train.optimizer=adamw",
                "data.augment.enabled=true",
            ),
            base="paper",
        ),
        Recipe(
            "default",
            "the `cpu` recipe's base (the network shipped until 2026-12-02): tiny RaFD at 256 px, 4 frames, flow at "
            "stride 8, 16-cell attention windows, gain-robust input, pre-norm propagation; AdamW 1e-3 with cosine "
            "decay, batch 4, 6 epochs, bf16-friendly; flip + rotation, radar intensity changes and crops up to 65 m "
            "from the radar (full-scan tiles)",
            (
                # The speed options (neither is the paper's), the gain-robust input, and pre-norm propagation blocks
                # that start as the identity (so a single-frame model's weights start a multi-frame run).
                "model.input_size=256",
                "model.input.normalisation=local_contrast",
                "model.input.window=47",
                "model.flow.stride=8",
                "model.enhance.window=16",
                "model.propagation.norm=pre",
                "train.epochs=6",
                "train.lr_schedule=cosine",
                "data.augment.intensity_probability=0.8",
                "data.augment.shift_probability=0.6",
                "data.augment.shift_max_m=65",
            ),
            base="tiny",
        ),
        Recipe(
            "cpu",
            "the default recipe's training with the network reshaped for a CPU: convolutional enhancement, a local "
            "cost volume without cross-attention, one joint propagation block over all past frames",
            (
                # docs/model.md, "The CPU network": residual dilated-convolution enhancement in place of window
                # attention, a local cost volume (radius 3 flow cells at stride 8: motions up to 4.2 m per frame,
                # 16.7 m/s at 4 Hz, relative to the static world) without the cross-attention blocks, and one joint
                # propagation block that samples all past frames at once, one point per frame, with a narrow FFN (a
                # fifth of the default's step); the input, backbone, neck and head are the default's.
                "model.enhance.kind=conv",
                "model.enhance.window=0",
                "model.flow.num_cross_blocks=0",
                "model.flow.local_radius=3",
                "model.flow.channels=8",
                "model.propagation.mode=joint",
                "model.propagation.num_blocks=1",
                "model.propagation.num_points=1",
                "model.propagation.ffn_ratio=1",
            ),
            base="default",
        ),
        Recipe(
            "cpu-narrow",
            "the `cpu` network at 16 feature channels instead of 32 (the shipped model's since 2026-12-08): about 0.6 "
            "of its step, so a 2-core replica holds whole scans of more radars; trained like it, its real fine-tune "
            "distilled from the wider model (rafd train --teacher)",
            ("model.neck.channels=16",),
            base="cpu",
        ),
    )
}


@cache
def recipe_config(name: str) -> RunConfig:
    """The run config of a recipe: its base's with its settings. The mixed-in data's augmentation is the recipe's
    own (data.mix_augment = data.augment), whatever a run later changes of data.augment."""
    if name not in RECIPES:
        raise ValueError(f"unknown recipe {name!r}; choose from {sorted(RECIPES)}")
    recipe = RECIPES[name]
    base = RunConfig() if recipe.base is None else recipe_config(recipe.base)
    config = base.overridden(parse_overrides(recipe.settings))
    return config.replace(data=dataclasses.replace(config.data, mix_augment=config.data.augment))


def recipe_model(name: str) -> RaFDConfig:
    """A recipe's network (the tests build recipes' networks with random weights)."""
    return recipe_config(name).model
