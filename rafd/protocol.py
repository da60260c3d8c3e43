"""What evaluation, serving and the service's clients must agree on, defined once (numpy-free, torch-free: the service
imports it).

- Which detections are answered: scores at or above the operating threshold (`OperatingThreshold`). A model carries
  its own, calibrated on validation data (`rafd-eval --calibrate` writes it into the checkpoint's meta,
  `rafd-export` into the ONNX metadata as text), optionally with a higher one for detections far from the radar
  (`rafd-eval --calibrate-far`: false positives grow with range, and real labels rarely reach that far); a model
  without one is read at DEFAULT_SCORE_THRESHOLD. `operating_threshold` is the one lookup, range-checked, used by
  `rafd-eval`, the plots, the MCAP logs and the service; rafd.detections.answered applies it.
- How detections are scored: oriented-box IoU thresholds of the benchmark protocol (TempoRadar, SIRA, RaFD) and the
  centre-matching distance.
- How much evidence the accuracy gate of a reduced precision needs (export/gate_report.py): fewer compared windows or
  fewer reference detections than GATE_MIN_FRAMES / GATE_MIN_REFERENCE_DETECTIONS is a FAIL ("too little to
  judge"), and the service (rafd.runtime.runners.gate_passed) never considers a precision whose recorded gate did
  not pass on at least that much.
- When a stream's answer is "warming up": fewer real frames than the model's window (the window is padded by
  repeating the oldest frame; rafd.model.RaFD.step).
- What a stream id may be (`STREAM_ID_PATTERN`, `STREAM_ID_MAX_LENGTH`): service/schemas.py's `StreamId` is built
  from it and the clients (rafd.detect_client, `rafd client`, the load benchmarks) name their streams by it, so a
  client cannot drift from what the server accepts.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

DEFAULT_SCORE_THRESHOLD = 0.3  # a model exported or saved without an operating threshold
IOU_THRESHOLDS = (0.3, 0.5, 0.7)  # mAP@0.3 / 0.5 / 0.7 on oriented boxes (polygon IoU, match when IoU > t)
CENTRE_DISTANCE_M = 2.0  # centre matching: a detection counts when its centre is within this of an unmatched vehicle's
OPERATING_THRESHOLD_KEY = "operating_threshold"  # checkpoint meta and ONNX metadata key
FAR_THRESHOLD_KEY = "operating_threshold_far"  # {"from_m": R, "threshold": T}: meta dict, ONNX metadata JSON text
# The accuracy gate judges on at least this many compared windows and reference detections (all sources together):
# its "changed detections" check (at most 2 %) needs 50 detections before one change is under the limit, and its
# p99 figures need about 100 matched pairs to mean more than the largest value. The default gate (12 simulated
# sequences of 60 frames) compares about 700 windows and 1900 detections on the shipped model.
GATE_MIN_FRAMES = 100
GATE_MIN_REFERENCE_DETECTIONS = 100


def check_score_threshold(value: Any, source: str) -> float:
    """A score threshold as a float in [0, 1]; ValueError naming `source` when it is not a number or out of range."""
    try:
        threshold = float(value)
    except (TypeError, ValueError) as error:
        raise ValueError(f"{source} is not a number: {value!r}") from error
    if not (math.isfinite(threshold) and 0.0 <= threshold <= 1.0):
        raise ValueError(f"{source} is outside [0, 1]: {threshold}")
    return threshold


@dataclass(frozen=True)
class OperatingThreshold:
    """The scores answered: at or above `near`, or at or above `far` for a detection whose centre lies `far_from_m`
    or farther from the radar (when the model has a far threshold)."""

    near: float
    far: float | None = None
    far_from_m: float | None = None

    def __post_init__(self) -> None:
        check_score_threshold(self.near, "the operating threshold")
        if (self.far is None) != (self.far_from_m is None):
            raise ValueError("a far threshold needs both its range and its threshold")
        if self.far is not None and self.far_from_m is not None:
            check_score_threshold(self.far, "the far operating threshold")
            if not (math.isfinite(self.far_from_m) and self.far_from_m > 0):
                raise ValueError(f"the far threshold's range must be a positive number of metres: {self.far_from_m}")

    @property
    def lowest(self) -> float:
        return self.near if self.far is None else min(self.near, self.far)

    def far_json(self) -> dict[str, float] | None:
        """FAR_THRESHOLD_KEY's value (None: one threshold at every range)."""
        if self.far is None or self.far_from_m is None:
            return None
        return {"from_m": self.far_from_m, "threshold": self.far}

    def __str__(self) -> str:
        if self.far is None:
            return f"{self.near:.3f}"
        return f"{self.near:.3f} within {self.far_from_m:g} m, {self.far:.3f} beyond"


def as_operating_threshold(threshold: OperatingThreshold | float) -> OperatingThreshold:
    """A plain number is one threshold at every range."""
    return threshold if isinstance(threshold, OperatingThreshold) else OperatingThreshold(float(threshold))


def far_threshold(value: Any) -> tuple[float, float] | None:
    """FAR_THRESHOLD_KEY's value (a dict, or its JSON text in ONNX metadata) -> (from_m, threshold); None when
    absent. ValueError when it is malformed."""
    if value is None:
        return None
    try:
        parsed = json.loads(value) if isinstance(value, str) else value
        return float(parsed["from_m"]), float(parsed["threshold"])
    except (TypeError, ValueError, KeyError) as error:
        raise ValueError(f"the model's {FAR_THRESHOLD_KEY} is not {{from_m, threshold}}: {value!r}") from error


def operating_threshold(meta: Mapping[str, Any] | None, override: float | None = None) -> OperatingThreshold:
    """The scores to answer at: `override` when given (a user's choice, at every range), else the model's documented
    operating threshold in `meta` (a checkpoint's meta dict or an ONNX model's metadata) with its far threshold when
    it has one, else DEFAULT_SCORE_THRESHOLD. ValueError when any is not a number in [0, 1]."""
    if override is not None:
        return OperatingThreshold(check_score_threshold(override, "the score threshold"))
    meta = meta or {}
    value = meta.get(OPERATING_THRESHOLD_KEY)
    if value is None:
        return OperatingThreshold(DEFAULT_SCORE_THRESHOLD)
    near = check_score_threshold(value, f"the model's {OPERATING_THRESHOLD_KEY}")
    far = far_threshold(meta.get(FAR_THRESHOLD_KEY))
    if far is None:
        return OperatingThreshold(near)
    return OperatingThreshold(near, far=far[1], far_from_m=far[0])


def warming_up(frames_used: int, num_frames: int) -> bool:
    """Whether a stream's window still holds fewer real frames than the model reads (its old end is padded)."""
    return frames_used < num_frames


# ----------------------------------------------------------------------------- the stream-id rule
STREAM_ID_MAX_LENGTH = 128
# URL-path-safe, printable, no whitespace: the id also appears in DELETE /streams/{stream_id}. As the inside of a
# regular-expression class, with and without ".".
_ID_CHARACTERS = r"A-Za-z0-9._~:@+\-"
_ID_CHARACTERS_BUT_DOT = r"A-Za-z0-9_~:@+\-"
# Neither "." nor "..", which a normalising proxy rewrites as path segments (`/streams/../detect` would become
# `/detect`): an id starts with a character other than ".", or with "." and one other, or with ".." and more.
STREAM_ID_PATTERN = (
    rf"^(?:[{_ID_CHARACTERS_BUT_DOT}][{_ID_CHARACTERS}]{{0,{STREAM_ID_MAX_LENGTH - 1}}}"
    rf"|\.[{_ID_CHARACTERS_BUT_DOT}][{_ID_CHARACTERS}]{{0,{STREAM_ID_MAX_LENGTH - 2}}}"
    rf"|\.\.[{_ID_CHARACTERS}]{{1,{STREAM_ID_MAX_LENGTH - 2}}})$"
)
STREAM_ID_RULE = f'1-{STREAM_ID_MAX_LENGTH} characters from A-Z a-z 0-9 . _ ~ : @ + -, and not "." or ".."'
_NOT_ID_CHARACTER = re.compile(f"[^{_ID_CHARACTERS}]")


def is_stream_id(text: str) -> bool:
    """Whether the service takes `text` as a stream id (the pattern bounds the length too)."""
    return re.fullmatch(STREAM_ID_PATTERN, text) is not None


def stream_id_from(name: str) -> str:
    """`name` with every character a stream id may not hold replaced by "_". Not cut to length, and "." or ".."
    stay as they are: callers add a suffix (a run id, a stream number) that makes the id valid."""
    return _NOT_ID_CHARACTER.sub("_", name)
