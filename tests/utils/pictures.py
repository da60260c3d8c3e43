"""Checking pictures: where a colour is drawn, on the RADIATE grid."""

from __future__ import annotations

import numpy as np

RES = 0.173611


def dominant(picture: np.ndarray, colour: tuple[int, int, int]) -> np.ndarray:
    """[H, W] mask of pixels close to a BGR colour (antialiased strokes blend at their edges)."""
    return (np.abs(picture.astype(int) - np.array(colour)) < 90).all(-1) & (picture.max(-1) > 120)
