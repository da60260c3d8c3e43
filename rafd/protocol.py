"""What evaluation, serving and the service's clients must agree on, defined once (numpy-free, torch-free: the service
imports it).

- Which detections are answered: scores at or above the operating threshold. A model carries its own, calibrated on
  validation data (`rafd-eval --calibrate` writes it into the checkpoint's meta, `rafd-export` into the ONNX
  metadata as text); a model without one is read at DEFAULT_SCORE_THRESHOLD. `operating_threshold` is the one
  lookup, range-checked, used by `rafd-eval`, the plots, the MCAP logs and the service.
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

import math
import re
from collections.abc import Mapping
from typing import Any

DEFAULT_SCORE_THRESHOLD = 0.3  # a model exported or saved without an operating threshold
IOU_THRESHOLDS = (0.3, 0.5, 0.7)  # mAP@0.3 / 0.5 / 0.7 on oriented boxes (polygon IoU, match when IoU > t)
CENTRE_DISTANCE_M = 2.0  # centre matching: a detection counts when its centre is within this of an unmatched vehicle's
OPERATING_THRESHOLD_KEY = "operating_threshold"  # checkpoint meta and ONNX metadata key
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


def operating_threshold(meta: Mapping[str, Any] | None, override: float | None = None) -> float:
    """The score threshold to answer at: `override` when given (a user's choice), else the model's documented
    operating threshold in `meta` (a checkpoint's meta dict or an ONNX model's metadata), else
    DEFAULT_SCORE_THRESHOLD. ValueError when either is not a number in [0, 1]."""
    if override is not None:
        return check_score_threshold(override, "the score threshold")
    value = (meta or {}).get(OPERATING_THRESHOLD_KEY)
    if value is None:
        return DEFAULT_SCORE_THRESHOLD
    return check_score_threshold(value, f"the model's {OPERATING_THRESHOLD_KEY}")


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
