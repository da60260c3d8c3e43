"""Decoding of the network's fixed-K outputs into detections (numpy only; shared with the service)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rafd.geometry import box_polygons_pixels
from rafd.protocol import DEFAULT_SCORE_THRESHOLD, OperatingThreshold


@dataclass(frozen=True)
class Detections:
    boxes: np.ndarray  # [N, 5] (x, y, width, length, yaw) metres / radians, ego frame
    scores: np.ndarray  # [N]
    labels: np.ndarray  # [N] int class indices

    def __len__(self) -> int:
        return len(self.scores)

    def as_array(self) -> np.ndarray:
        """[N, 6] (x, y, width, length, yaw, score), the metrics' prediction format."""
        return np.concatenate([self.boxes, self.scores[:, None]], 1)

    def polygons(self, image_size: int, resolution: float) -> np.ndarray:
        """[N, 4, 2] corner pixels in a square image of `image_size` centred on the radar."""
        return box_polygons_pixels(self.boxes, image_size, resolution)


def decode_detections(
    boxes: np.ndarray,
    scores: np.ndarray,
    score_threshold: float = DEFAULT_SCORE_THRESHOLD,
    labels: np.ndarray | None = None,
) -> Detections:
    """Fixed-K outputs (boxes [K, 5], scores [K]) -> detections above the threshold, best first.

    The graph always emits K candidates (no data-dependent shapes); thresholding happens here.
    """
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 5)
    scores = np.asarray(scores, dtype=np.float64).reshape(-1)
    if len(boxes) != len(scores):
        raise ValueError(f"{len(boxes)} boxes but {len(scores)} scores")
    labels = np.zeros(len(scores), dtype=np.int64) if labels is None else np.asarray(labels, dtype=np.int64)
    keep = np.flatnonzero(np.isfinite(scores) & (scores >= score_threshold))
    keep = keep[np.argsort(-scores[keep], kind="stable")]
    return Detections(boxes=boxes[keep], scores=scores[keep], labels=labels[keep])


def answered_mask(centres: np.ndarray, scores: np.ndarray, threshold: OperatingThreshold | float) -> np.ndarray:
    """Centres [N, 2] (metres from the radar), scores [N] -> [N] bool: the detections the threshold answers (its far
    threshold applies from its range outwards)."""
    centres = np.asarray(centres, np.float64).reshape(-1, 2)
    scores = np.asarray(scores, np.float64).reshape(-1)
    if not isinstance(threshold, OperatingThreshold):  # a swept number (evaluation), possibly just above 1
        return np.isfinite(scores) & (scores >= threshold)
    cut = np.full(len(scores), threshold.near)
    if threshold.far is not None and threshold.far_from_m is not None:
        cut[np.hypot(centres[:, 0], centres[:, 1]) >= threshold.far_from_m] = threshold.far
    return np.isfinite(scores) & (scores >= cut)


def answered(predictions: np.ndarray, threshold: OperatingThreshold | float) -> np.ndarray:
    """Predictions [N, 6] (x, y, width, length, yaw, score; centres from the radar) -> the rows answered."""
    predictions = np.asarray(predictions).reshape(-1, 6)
    return predictions[answered_mask(predictions[:, :2], predictions[:, 5], threshold)]
