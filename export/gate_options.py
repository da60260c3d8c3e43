"""What an accuracy gate is asked: its limits (GateThresholds) and, for `rafd export --gate` and `rafd gate`, its
size, seeds and islands search (GateOptions)."""

from __future__ import annotations

from dataclasses import dataclass

from export.quantize import CALIBRATION_FRAMES, CALIBRATION_SEQUENCES
from rafd.protocol import DEFAULT_SCORE_THRESHOLD, GATE_MIN_FRAMES, GATE_MIN_REFERENCE_DETECTIONS

DEFAULT_SEED = 7100  # not a seed of rafd bench accuracy's data (1000 train, 2000 test); override if a model saw it


@dataclass(frozen=True)
class GateThresholds:
    score_threshold: float = DEFAULT_SCORE_THRESHOLD  # detections compared are those at or above it
    changed_fraction: float = 0.02  # of the reference's detections
    centre_p99_m: float = 0.05
    score_p99: float = 0.02
    map_points: float = 0.5  # per IoU threshold, in mAP points (percent)
    epe_m: float = 0.01
    # the evidence needed before the gate judges at all (all sources together); lower only in tests of the checks
    min_frames: int = GATE_MIN_FRAMES
    min_reference_detections: int = GATE_MIN_REFERENCE_DETECTIONS


@dataclass(frozen=True)
class GateOptions:
    # ~700 compared windows: with fewer (222), bf16's flips of single boxes across IoU 0.7 moved mAP by a point or
    # more either way
    sequences: int = 12
    frames: int = 60
    seed: int = DEFAULT_SEED
    threads: int | None = None
    thresholds: GateThresholds = GateThresholds()
    # where plain bf16 or int8 fails: search for float32 islands that pass (export/islands_gate.py), trying each unit
    # on a short gate of search_sequences x search_frames (other simulated drives than the gate's)
    islands: bool = True
    search_sequences: int = 2
    search_frames: int = 40
    # int8's activation statistics: simulated sequences of their own seed (export.quantize.CALIBRATION_SEED)
    calibration_sequences: int = CALIBRATION_SEQUENCES
    calibration_frames: int = CALIBRATION_FRAMES
