"""Decode and validate posted radar frames: 8-bit single-channel PNG, full RADIATE scan or model size."""
from __future__ import annotations

import base64
import binascii
import struct
from dataclasses import dataclass

import cv2
import numpy as np

from rafd.geometry import RADIATE_RESOLUTION, RADIATE_SCAN_SIZE
from rafd.preprocess import model_crop, to_model_input
from service.errors import ApiError

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# Odometry registers this much of the posted scan around the radar (89 m at RADIATE's resolution):
# on the model's small crop alone the static scene is too sparse and registration sometimes locks
# onto vehicles that move with the ego.
ODOMETRY_VIEW_SIZE = 512


@dataclass(frozen=True)
class DecodedFrame:
    crop: np.ndarray  # [S, S] uint8, the model's input crop centred on the radar
    posted_size: int  # side of the posted image (polygons are answered in its pixels)
    crop_offset: int  # posted pixel of the crop's top-left corner (0 when posted at model size)
    odometry_view: np.ndarray  # [V, V] uint8 centre of the posted image that odometry registers (V >= S)

    def model_input(self) -> np.ndarray:
        """[S, S] uint8 -> [S, S] float32 in [0, 1], the runner's frame."""
        return to_model_input(self.crop)


def accepted_sizes(input_size: int, resolution: float) -> tuple[int, ...]:
    """Square sides accepted: the model's input, plus a full RADIATE scan when the model runs at its resolution."""
    sizes = [input_size]
    if input_size < RADIATE_SCAN_SIZE and abs(resolution - RADIATE_RESOLUTION) < 1e-6:
        sizes.append(RADIATE_SCAN_SIZE)
    return tuple(sizes)


def decode_base64(text: str) -> bytes:
    """Base64 text (optionally a `data:image/png;base64,` URL) -> bytes; 422 when it is not base64."""
    if text.startswith("data:"):
        text = text.partition(",")[2]
    try:
        return base64.b64decode(text, validate=True)
    except (binascii.Error, ValueError) as exc:
        raise ApiError(422, "invalid_image", f"field 'image' is not valid base64: {exc}") from exc


def png_header_size(data: bytes) -> tuple[int, int]:
    """(width, height) from the PNG IHDR chunk, read before decoding so a huge image is never allocated."""
    if not data:
        raise ApiError(422, "invalid_image", "the image is empty")
    if not data.startswith(PNG_SIGNATURE) or len(data) < 24 or data[12:16] != b"IHDR":
        raise ApiError(422, "invalid_image", "the image is not a PNG (expected the PNG signature and IHDR chunk)")
    width, height = struct.unpack(">II", data[16:24])
    return width, height


def decode_frame(data: bytes, input_size: int, resolution: float) -> DecodedFrame:
    """PNG bytes -> the model's [S, S] uint8 crop; 422 naming what was expected on any mismatch."""
    width, height = png_header_size(data)
    sizes = accepted_sizes(input_size, resolution)
    if width != height or width not in sizes:
        accepted = " or ".join(f"{s}x{s}" for s in sizes)
        raise ApiError(422, "unsupported_image_size", f"image is {width}x{height}; accepted sizes: {accepted}")
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ApiError(422, "invalid_image", "the PNG could not be decoded (truncated or corrupt)")
    if image.ndim != 2:
        channels = image.shape[2] if image.ndim == 3 else "?"
        raise ApiError(422, "unsupported_image_format",
                       f"image has {channels} channels; expected a single-channel (greyscale) radar scan")
    if image.dtype != np.uint8:
        raise ApiError(422, "unsupported_image_format",
                       f"image is {image.dtype}; expected 8-bit greyscale like RADIATE's Navtech scans")
    view = model_crop(image, max(input_size, min(width, ODOMETRY_VIEW_SIZE)))
    return DecodedFrame(crop=model_crop(image, input_size), posted_size=width, crop_offset=(width - input_size) // 2,
                        odometry_view=view)
