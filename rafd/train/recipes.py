"""Named training recipes: a network config, the optimisation settings and whether to augment, in one name.

`rafd-train --config NAME` starts from the recipe; any flag given on the command line overrides its field, and the
checkpoint records the recipe's name and every resulting setting (rafd.train.trainer.Trainer.save).
"""
from __future__ import annotations

from dataclasses import dataclass

from rafd.config import RaFDConfig
from rafd.train.trainer import TrainConfig


@dataclass(frozen=True)
class Recipe:
    name: str
    description: str
    model: RaFDConfig
    train: TrainConfig
    augment: bool  # window-consistent flip + rotation (rafd.augment)


RECIPES: dict[str, Recipe] = {
    recipe.name: recipe
    for recipe in (
        Recipe(
            "paper",
            "the paper's setting (section 3): ResNet-34 RaFD, 256 px crop, 4 frames; Adam, lr 2e-4, weight decay 1e-2, "
            "global batch 8, 10 epochs; no augmentation, no learning-rate schedule (the paper states none)",
            RaFDConfig.paper(),
            TrainConfig(epochs=10, batch_size=8, lr=2e-4, weight_decay=1e-2, optimizer="adam", lr_schedule="constant"),
            augment=False,
        ),
        Recipe(
            "tiny",
            "every part of RaFD small enough for a CPU (128 px crop, 4 frames); AdamW, lr 1e-3, weight decay 1e-2, "
            "batch 4, 8 epochs, flip + rotation augmentation (the synthetic benchmark's setting)",
            RaFDConfig.tiny(),
            TrainConfig(epochs=8, batch_size=4, lr=1e-3, weight_decay=1e-2, optimizer="adamw", lr_schedule="constant"),
            augment=True,
        ),
    )
}
