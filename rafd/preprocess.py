"""The one torch-free path from a radar scan to the model's input frame.

Training (rafd.data.dataset, rafd.data.collate), export verification, the benchmarks and the service all
call these functions, so what the network sees cannot drift between them:

    polar uint8 [576, 400] (the sensor's native scan, RADIATE's Navtech_Polar layout; optional first step)
      -> polar_to_cartesian uint8 [1152, 1152] (rafd.scans.polar: RADIATE's conventions, opencv remap)
    scan uint8 [N, N] (RADIATE Cartesian grid, radar at the centre)
      -> model_crop      uint8 [S, S], the centre S x S pixels (S = the model's input_size)
      -> to_model_input  float32 [S, S] in [0, 1] (grey / 255)

Anything that depends on the scan's intensity statistics (gain-robust normalisation) is the network's first
module, so PyTorch and the exported ONNX graph compute it identically from this [0, 1] frame.
"""

from __future__ import annotations

import math

import numpy as np

from rafd.scans.polar import polar_to_cartesian  # the polar step of this path, re-exported

__all__ = ["GREY_LEVELS", "model_crop", "model_crop_of_top_rows", "model_frame", "polar_to_cartesian", "to_model_input"]

GREY_LEVELS = 255.0  # RADIATE's scans are 8-bit


def model_crop(scan: np.ndarray, input_size: int) -> np.ndarray:
    """uint8 [N, N] scan -> uint8 [S, S] centre crop around the radar (a contiguous copy-free view when possible)."""
    scan = np.asarray(scan)
    if scan.ndim != 2 or scan.shape[0] != scan.shape[1]:
        raise ValueError(f"expected a square 2-D scan with the radar at the centre, got shape {scan.shape}")
    return model_crop_of_top_rows(scan, input_size)


def model_crop_of_top_rows(scan_top: np.ndarray, input_size: int) -> np.ndarray:
    """uint8 [R, N] top rows (R <= N) of an [N, N] scan centred on the radar -> the same [S, S] centre crop as
    model_crop of the whole scan, which must lie within those rows (the service decodes a posted scan only down to
    the last row it reads)."""
    side = scan_top.shape[1]
    if input_size > side:
        raise ValueError(f"cannot crop {input_size}x{input_size} from a {scan_top.shape[0]}x{side} image")
    if (side - input_size) % 2:
        raise ValueError(f"a {side} px scan cannot be centre-cropped to {input_size} px (odd difference)")
    top = (side - input_size) // 2
    if top + input_size > scan_top.shape[0]:
        raise ValueError(f"the {input_size} px centre crop reaches past the {scan_top.shape[0]} x {side} px given")
    return np.ascontiguousarray(scan_top[top : top + input_size, top : top + input_size])


def rotation_crop(input_size: int) -> int:
    """Smallest even centre crop from which an input_size crop turned by any angle can be cut (rafd.data.augment warps
    from exactly this crop, so a prepared cache and the full scan give identical windows)."""
    side = math.ceil(input_size * math.sqrt(2.0)) + 2  # + 2: bilinear neighbours of the corner pixels
    return side + side % 2


def to_model_input(crop: np.ndarray) -> np.ndarray:
    """uint8 [..., S, S] -> float32 [..., S, S] in [0, 1], the network's frame."""
    crop = np.asarray(crop)
    if crop.dtype != np.uint8:
        raise ValueError(f"radar frames are 8-bit greyscale; got {crop.dtype}")
    return crop.astype(np.float32) * np.float32(1.0 / GREY_LEVELS)


def model_frame(scan: np.ndarray, input_size: int) -> np.ndarray:
    """uint8 [N, N] scan -> float32 [S, S] model input (model_crop then to_model_input)."""
    return to_model_input(model_crop(scan, input_size))
