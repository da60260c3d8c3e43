"""The shipped default model is what the `cpu` recipe trains, calibrated on validation data; the `cpu` recipe's
network trains a step like every other config."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import torch

from rafd.assets import default_checkpoint
from rafd.config import RaFDConfig
from rafd.data.collate import Collator
from rafd.data.windows import open_windows
from rafd.model.checkpoint import load_checkpoint
from rafd.train.config import RunConfig, TrainConfig
from rafd.train.distributed import DistContext
from rafd.train.losses import LOSS_TERMS
from rafd.train.recipes import recipe_model
from rafd.train.trainer import Trainer


def test_the_shipped_checkpoint_is_the_narrow_cpu_recipes_network_calibrated_on_a_validation_split() -> None:
    _, cfg, meta = load_checkpoint(default_checkpoint())
    assert cfg == recipe_model("cpu-narrow")
    threshold = meta["operating_threshold"]
    assert math.isfinite(threshold) and 0.0 < threshold < 1.0
    point = meta["operating_point"]
    # the threshold was chosen on validation whole scans (the real Oxford validation scans), never on a test split
    assert point["full_scan"] and "test" not in point["split"] and point["fp_per_frame_budget"] > 0


def test_the_cpu_network_trains_a_step(tiny_root: Path, tiny_cfg: RaFDConfig) -> None:
    cpu = recipe_model("cpu")
    # the cpu recipe's parts on the tiny fixture's size and frame count
    cfg = tiny_cfg.replace(
        enhance=dataclasses.replace(tiny_cfg.enhance, kind="conv", window=0),
        flow=dataclasses.replace(tiny_cfg.flow, num_cross_blocks=0, local_radius=2, channels=cpu.flow.channels),
        propagation=dataclasses.replace(cpu.propagation),
    )
    dataset = open_windows(tiny_root, "train", cfg)
    train = TrainConfig(epochs=1, batch_size=2, seed=3, device="cpu", progress=False, val_every=0, lr=2e-3)
    trainer = Trainer(RunConfig(model=cfg, train=train), dataset, None, DistContext())
    batch = Collator(cfg)([dataset[i] for i in range(2)])
    before = {k: v.detach().clone() for k, v in trainer.model.state_dict().items()}
    losses = trainer.train_step(batch)
    assert torch.isfinite(losses[LOSS_TERMS.index("total")]) and losses[LOSS_TERMS.index("flow")] > 0
    moved = [k for k, v in trainer.model.state_dict().items() if not torch.equal(v, before[k])]
    assert any("propagation" in k for k in moved) and any("flow" in k for k in moved)


def test_recipes_are_settings_on_top_of_each_other() -> None:
    """`paper` is the config's defaults, `tiny` the tiny network (RaFDConfig.tiny), and each recipe's mixed-in data
    are augmented as its own."""
    from rafd.train.config import RunConfig
    from rafd.train.recipes import RECIPES, recipe_config

    assert recipe_config("paper") == RunConfig()
    assert recipe_config("tiny").model == RaFDConfig.tiny()
    for name in RECIPES:
        config = recipe_config(name)
        assert config.data.mix_augment == config.data.augment, name
    default, cpu = recipe_config("default"), recipe_config("cpu")
    assert (default.train, default.data) == (cpu.train, cpu.data)  # cpu reshapes the network only
