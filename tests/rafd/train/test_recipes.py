"""The shipped default model is what the `default` recipe trains, calibrated on validation data."""

from __future__ import annotations

import math

from rafd.assets import default_checkpoint
from rafd.checkpoint import load_checkpoint
from rafd.train.recipes import RECIPES, shipped_model_config


def test_the_shipped_checkpoint_is_the_default_recipes_network_calibrated_on_a_validation_split() -> None:
    _, cfg, meta = load_checkpoint(default_checkpoint())
    assert cfg == shipped_model_config() == RECIPES["default"].model
    threshold = meta["operating_threshold"]
    assert math.isfinite(threshold) and 0.0 < threshold < 1.0
    point = meta["operating_point"]
    # the threshold was chosen on validation whole scans (the real Oxford validation scans), never on a test split
    assert point["full_scan"] and "test" not in point["split"] and point["fp_per_frame_budget"] > 0
