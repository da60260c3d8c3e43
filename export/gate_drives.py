"""The frames an accuracy gate streams: simulated held-out drives (rafd.sim, a seed the model was not trained on,
labelled under the benchmark protocol via rafd.data.RadarWindowDataset) and the real RADIATE sample's frames
(images only; poses by radar odometry; no labels, so only the comparisons with the reference)."""

from __future__ import annotations

import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rafd.config import RaFDConfig


@dataclass
class LabelledFrame:
    frame: np.ndarray  # float32 [S, S] model input
    pose: np.ndarray  # float64 [3] world pose
    boxes: np.ndarray | None = None  # [M, 5] protocol GT of this frame (None: no labels or warm-up frame)
    gt_flow: np.ndarray | None = None  # [2, Hf, Wf] pseudo-GT flow of the newest pair
    flow_valid: np.ndarray | None = None  # [Hf, Wf] cells with a defined flow target


def simulated_sequences(cfg: RaFDConfig, sequences: int, frames: int, seed: int) -> Iterator[list[LabelledFrame]]:
    """Simulate held-out sequences (rafd.sim, scans of max(256, S) px) and yield each one's frames in order,
    labelled under the benchmark protocol from frame T on (earlier frames only warm the stream up)."""
    from rafd.data.dataset import RadarWindowDataset
    from rafd.data.targets import build_targets
    from rafd.preprocess import to_model_input
    from rafd.sim.api import simulate_dataset

    with tempfile.TemporaryDirectory(prefix="rafd-gate-") as tmp:
        simulate_dataset(tmp, sequences, frames, seed, split="test", size=max(256, cfg.input_size))
        dataset = RadarWindowDataset(tmp, split="test", cfg=cfg)
        current: list[LabelledFrame] = []
        previous_key = None
        for index in range(len(dataset)):
            window = dataset.window(index)
            key = (window["sequence"], window["frame"])
            if previous_key is None or key[0] != previous_key[0] or key[1] != previous_key[1] + 1:
                if current:
                    yield current
                # a new stream: the window's older frames first (unlabelled warm-up)
                current = [
                    LabelledFrame(to_model_input(f), p) for f, p in zip(window["frames"][:-1], window["poses"][:-1])
                ]
            previous_key = key
            targets = build_targets(window["boxes"], window["ids"], window["poses"], cfg)
            current.append(
                LabelledFrame(
                    to_model_input(window["frames"][-1]),
                    window["poses"][-1],
                    np.asarray(window["boxes"][-1]).reshape(-1, 5),
                    targets["flow"][-1] if len(targets["flow"]) else None,
                    targets["flow_valid"][-1, 0] if len(targets["flow_valid"]) else None,
                )
            )
        if current:
            yield current


def radiate_frames(folder: str | Path, cfg: RaFDConfig, length: int = 1000) -> list[LabelledFrame]:
    """A real RADIATE sequence's frames (images only, poses by odometry), unlabelled."""
    from export.verify import radiate_sequence

    frames, poses = radiate_sequence(folder, cfg, length)
    return [LabelledFrame(f, p) for f, p in zip(frames, poses)]
