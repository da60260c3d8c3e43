"""The answer's flow as PNG (flow_format=png): a whole scan's flow in a few hundred kilobytes, lossless to 1 mm.

values: one 16-bit greyscale PNG of [2 H, W] pixels, the flow's x rows over its y rows, each pixel the flow in
millimetres plus OFFSET_MM (0 m is 32768; +-32.7 m, far beyond what a scan-to-scan motion reaches). validity: one
8-bit greyscale PNG of [H, W], each pixel k with validity k / 100. Both base64 in the JSON answer. Written once for the
service (encode) and the clients (decode); opencv reads and writes them.
"""

from __future__ import annotations

import cv2
import numpy as np

OFFSET_MM = 32768


def encode_flow(flow: np.ndarray) -> bytes:
    """[2, H, W] metres -> the PNG's bytes."""
    _, height, width = flow.shape
    millimetres = np.clip(np.round(np.asarray(flow, np.float64) * 1000.0) + OFFSET_MM, 0, 65535).astype(np.uint16)
    return _png(millimetres.reshape(2 * height, width))


def decode_flow(data: bytes, shape: tuple[int, int, int]) -> np.ndarray:
    """The PNG's bytes -> float64 [2, H, W] metres."""
    pixels = _read(data, np.uint16)
    return (pixels.astype(np.float64) - OFFSET_MM).reshape(shape) / 1000.0


def encode_steps(steps: np.ndarray) -> bytes:
    """[H, W] integers k in [0, 100] (validity k / 100) -> the PNG's bytes."""
    return _png(np.asarray(steps).astype(np.uint8))


def decode_steps(data: bytes, shape: tuple[int, int]) -> np.ndarray:
    """The PNG's bytes -> float64 [H, W] validity in [0, 1]."""
    return _read(data, np.uint8).reshape(shape).astype(np.float64) / 100.0


def _png(pixels: np.ndarray) -> bytes:
    ok, encoded = cv2.imencode(".png", pixels, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise ValueError(f"could not encode a {pixels.dtype} {pixels.shape} PNG")
    return encoded.tobytes()


def _read(data: bytes, dtype: type) -> np.ndarray:
    pixels = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if pixels is None or pixels.dtype != dtype or pixels.ndim != 2:
        raise ValueError(f"not a greyscale {np.dtype(dtype).name} PNG")
    return pixels
