"""RADIATE's Cartesian scans (`Navtech_Cartesian/NNNNNN.png`): 8-bit grey [S, S] PNGs, RADIATE_RESOLUTION metres per
pixel, the radar at the image centre, x right, y forward = image up (rafd.geometry holds the grid; S = 1152 for
RADIATE). Polar and native scans (rafd.scans.polar, rafd.scans.native) are converted to this form, and the model's
crop is cut from its centre (rafd.preprocess).

`load_image` reads a scan PNG's grey pixels (RADIATE's polar PNGs and the native scans are read with it too),
`png_size` its size from the header alone; `accepted_sizes` says which Cartesian sides a model takes.
"""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np

from rafd.geometry import RADIATE_RESOLUTION, RADIATE_SCAN_SIZE

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def load_image(path: str | Path, flags: int = cv2.IMREAD_GRAYSCALE, what: str = "radar image") -> np.ndarray:
    """uint8 [H, W] grey image (cv2.imread `flags`: native scans are read unchanged); FileNotFoundError / ValueError
    naming the file (as `what`) when missing or undecodable."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} {path} not found")
    image = cv2.imread(str(path), flags)
    if image is None:
        raise ValueError(f"{what} {path} is corrupt or not an image (cv2.imread failed)")
    return image


def png_size(path: Path) -> tuple[int, int]:
    """(width, height) from a PNG's IHDR header (24 bytes read); ValueError naming the file if not a PNG."""
    try:
        with path.open("rb") as handle:
            head = handle.read(24)
    except FileNotFoundError:
        raise FileNotFoundError(f"radar image {path} not found") from None
    except OSError as error:
        raise ValueError(f"radar image {path} cannot be read ({error})") from error
    if len(head) < 24 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
        raise ValueError(f"radar image {path} is corrupt or not a PNG (bad header)")
    width, height = struct.unpack(">II", head[16:24])
    return int(width), int(height)


def accepted_sizes(input_size: int, resolution: float) -> tuple[int, ...]:
    """Square sides accepted: the model's input, plus a full RADIATE scan when the model runs at its resolution."""
    sizes = [input_size]
    if input_size < RADIATE_SCAN_SIZE and abs(resolution - RADIATE_RESOLUTION) < 1e-6:
        sizes.append(RADIATE_SCAN_SIZE)
    return tuple(sizes)
