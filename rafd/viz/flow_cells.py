"""Which flow cells get an arrow: those with returns to follow or near a box (meaningful_cells), and only valid
ones where the flow's validity is known (valid_cells)."""

from __future__ import annotations

import numpy as np

from rafd.flow_validity import FLOW_VALID_MIN

RETURNS_PERCENTILE = 95.0  # a cell holds returns when its brightest pixel reaches the image's 95th percentile ...
MIN_RETURN_LEVEL = 60  # ... and at least this grey level (a dark scan's percentile is still noise)
NEAR_BOX_M = 3.0  # cells whose centre is within this of a box centre (predicted or labelled) are drawn too


def meaningful_cells(
    image: np.ndarray,
    shape: tuple[int, int],
    stride: int,
    origin: tuple[float, float] = (0.0, 0.0),
    centres: np.ndarray | None = None,
    near_px: float = 0.0,
) -> np.ndarray:
    """[Hf, Wf] bool: the flow cells worth an arrow. A cell's flow is estimated everywhere, but it means something
    only where the scan has returns to follow or near an object; elsewhere (empty sky, the crop's padded edges) it is
    the network's extrapolation. `image`: the scan the grid lies on (uint8); cell (i, j) covers image pixels
    [origin_u + j*stride, +stride) x [origin_v + i*stride, +stride); `centres`: [N, 2] box centres (u, v) in image
    pixels, cells within `near_px` of one kept whatever their returns."""
    height, width = shape
    pixels = np.asarray(image, dtype=np.float32)
    level = max(float(np.percentile(pixels, RETURNS_PERCENTILE)), float(MIN_RETURN_LEVEL))
    u0, v0 = int(round(origin[0])), int(round(origin[1]))
    keep = np.zeros((height, width), dtype=bool)
    if u0 >= 0 and v0 >= 0:
        block = pixels[v0 : v0 + height * stride, u0 : u0 + width * stride]
        if block.shape == (height * stride, width * stride):
            keep |= block.reshape(height, stride, width, stride).max(axis=(1, 3)) >= level
    if centres is not None and len(centres) and near_px > 0:
        u = origin[0] + (np.arange(width) + 0.5) * stride
        v = origin[1] + (np.arange(height) + 0.5) * stride
        grid = np.stack(np.meshgrid(u, v), -1)  # [Hf, Wf, 2] (u, v)
        distance = np.linalg.norm(grid[:, :, None, :] - np.asarray(centres, np.float64)[None, None], axis=-1)
        keep |= distance.min(axis=-1) <= near_px
    return keep


def valid_cells(validity: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray | None:
    """[Hf, Wf] bool: the cells whose flow validity (rafd.flow_validity) reaches FLOW_VALID_MIN, the only ones
    given an arrow; None when no validity is given (every cell may be drawn)."""
    if validity is None:
        return None
    valid = np.asarray(validity, dtype=np.float64)
    if valid.shape != tuple(shape):
        raise ValueError(f"validity of shape {valid.shape} for a flow grid of {tuple(shape)}")
    return valid >= FLOW_VALID_MIN
