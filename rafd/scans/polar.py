"""The Navtech's native polar scans -> RADIATE's Cartesian grid (opencv remap), with RADIATE's conventions.

RADIATE stores each scan as `Navtech_Polar/NNNNNN.png`: uint8 [576, 400] = [range bins, azimuths].
Conventions, established on the two real polar scans of tiny_foggy against the Cartesian images RADIATE made
from them (docs/data.md "Polar scans"; `rafd-polar` prints the agreement):

- rows are range: row i is the return at (i + 0.21) x 0.173611 m (576 bins, 0-100 m);
- columns are azimuth: 400 per turn (0.9 deg), counted CLOCKWISE seen from above, starting at the
  vehicle's forward direction (image up): column 0 lies just right of forward, 100 points right (+x),
  200 backwards, 300 left; column j is sampled at (j + 0.41) x 0.9 deg;
- in the 1152 x 1152 Cartesian image the radar sits at continuous pixel (575.5, 576.5): half a pixel
  left of and below the geometric centre (576, 576) that rafd.geometry assumes (8.7 cm; RADIATE's labels
  were drawn on these images, so the converted image keeps RADIATE's grid);
- bilinear interpolation, interpolating across the 399 -> 0 seam (RADIATE's images keep a hard seam there).

The sample offsets 0.41 / 0.21 (not the bin centres 0.5 / 0.5) and the radar's pixel come from a search that
minimises the mean absolute grey difference (`rafd-polar ... --fit`: frame 1 gives 0.414 / 0.219, frame 2
0.414 / 0.242, both the same centre); they cut that difference from 4.3 to 3.1 grey levels on both frames.
RADIATE's residual (correlation 0.974) is its own resampling, which bilinear sampling does not reproduce. The
simulator's sensor has its own conventions (`NavtechSensor.polar_conventions`); `to_radiate_polar` resamples
any polar scan onto RADIATE's.

Reading: a polar-only folder's scans (rafd.data.folders) load through `PolarSource`, which converts each PNG on load;
a posted scan of RADIATE_POLAR_SHAPE is one wherever a full RADIATE scan is accepted (`accepts_polar`).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from rafd.geometry import RADIATE_RESOLUTION, RADIATE_SCAN_SIZE
from rafd.scans.cartesian import accepted_sizes, load_image

RADIATE_RANGE_BINS = 576  # rows of a RADIATE polar scan: 0-100 m
RADIATE_AZIMUTHS = 400  # columns: one turn
# (height, width) of a RADIATE polar scan, its Navtech_Polar PNGs as they are on disk: (range bins, azimuths).
RADIATE_POLAR_SHAPE = (RADIATE_RANGE_BINS, RADIATE_AZIMUTHS)


@dataclass(frozen=True)
class PolarConventions:
    """Where each sample of a polar scan [range bins, azimuths] lies around the radar."""

    azimuth_offset: float = 0.41  # column j is sampled (j + this) azimuth steps clockwise from forward
    range_offset: float = 0.21  # row i is sampled (i + this) range bins from the radar
    range_bin: float = RADIATE_RESOLUTION  # metres per row
    # The radar's continuous pixel (u, v) in a Cartesian image of side S, minus (S/2, S/2).
    centre_offset: tuple[float, float] = (-0.5, 0.5)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.range_bin) and self.range_bin > 0):
            raise ValueError(f"range_bin must be a positive number of metres, got {self.range_bin}")


RADIATE_POLAR = PolarConventions()
# The textbook reading (samples at bin centres, radar at the image centre): kept to show what the fit buys.
NOMINAL_POLAR = PolarConventions(azimuth_offset=0.5, range_offset=0.5, centre_offset=(0.0, 0.0))


def cartesian_size(
    range_bins: int, resolution: float = RADIATE_RESOLUTION, conventions: PolarConventions = RADIATE_POLAR
) -> int:
    """Even side in pixels of the Cartesian image that holds the whole polar disc (RADIATE: 576 bins -> 1152)."""
    radius = range_bins * conventions.range_bin / resolution
    return 2 * int(math.ceil(radius - 1e-6))


def _check_polar(polar: np.ndarray) -> np.ndarray:
    polar = np.asarray(polar)
    if polar.ndim != 2 or min(polar.shape) < 2:
        raise ValueError(f"a polar scan is a 2-D [range bins, azimuths] array, got shape {polar.shape}")
    if polar.dtype != np.uint8 and not np.issubdtype(polar.dtype, np.floating):
        raise ValueError(f"a polar scan holds 8-bit or float grey levels, got {polar.dtype}")
    return polar


def _wrapped(polar: np.ndarray) -> np.ndarray:
    """[R, A] -> float32 [R, A + 1]: azimuth 0 repeated after the last column so bilinear crosses the seam."""
    return np.concatenate([polar, polar[:, :1]], axis=1).astype(np.float32)


@functools.lru_cache(maxsize=8)
def _cartesian_maps(
    range_bins: int, azimuths: int, size: int, resolution: float, conventions: PolarConventions
) -> tuple[np.ndarray, np.ndarray]:
    """Per Cartesian pixel centre: (azimuth column, range row) it samples in the wrapped polar, float32 [S, S] each."""
    centres = np.arange(size, dtype=np.float64) + 0.5
    x = (centres - (size / 2.0 + conventions.centre_offset[0])) * resolution  # [S] metres right
    y = ((size / 2.0 + conventions.centre_offset[1]) - centres) * resolution  # [S] metres forward (image up)
    x, y = np.meshgrid(x, y, indexing="xy")  # [S, S] each
    clockwise = np.mod(np.arctan2(x, y), 2.0 * np.pi)  # from forward towards right: the sweep direction
    column = np.mod(clockwise / (2.0 * np.pi) * azimuths - conventions.azimuth_offset, azimuths)
    # Inside the first sample's range there is no data: take the first bin rather than fading to black.
    row = np.maximum(np.hypot(x, y) / conventions.range_bin - conventions.range_offset, 0.0)
    map_x, map_y = column.astype(np.float32), row.astype(np.float32)
    map_x.flags.writeable = map_y.flags.writeable = False  # shared by every call through the cache
    return map_x, map_y


def polar_to_cartesian(
    polar: np.ndarray,
    size: int | None = None,
    resolution: float = RADIATE_RESOLUTION,
    conventions: PolarConventions = RADIATE_POLAR,
) -> np.ndarray:
    """Polar scan [range bins, azimuths] (uint8 or float grey) -> uint8 [S, S] Cartesian scan, radar near the
    centre (exactly where `conventions` put it), x right, y forward = image up; black beyond the last bin.

    size defaults to the whole disc (cartesian_size: 1152 for RADIATE); resolution is metres per pixel.
    """
    polar = _check_polar(polar)
    if not (math.isfinite(resolution) and resolution > 0):
        raise ValueError(f"resolution must be a positive number of metres per pixel, got {resolution}")
    range_bins, azimuths = polar.shape
    size = cartesian_size(range_bins, resolution, conventions) if size is None else int(size)
    if size < 2 or size % 2:
        raise ValueError(f"the Cartesian side must be an even number of pixels >= 2, got {size}")
    map_x, map_y = _cartesian_maps(range_bins, azimuths, size, float(resolution), conventions)
    image = cv2.remap(_wrapped(polar), map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def to_radiate_polar(
    polar: np.ndarray,
    conventions: PolarConventions,
    range_bins: int = RADIATE_RANGE_BINS,
    azimuths: int = RADIATE_AZIMUTHS,
) -> np.ndarray:
    """Polar scan [R, A] sampled under `conventions` -> uint8 [range_bins, azimuths] in RADIATE's layout, bin size
    and sample positions (bilinear; zero beyond the source's last bin). The simulator writes Navtech_Polar with it."""
    polar = _check_polar(polar)
    source_bins, source_azimuths = polar.shape
    target = RADIATE_POLAR
    metres = (np.arange(range_bins, dtype=np.float64) + target.range_offset) * target.range_bin  # [R_t]
    turns = (np.arange(azimuths, dtype=np.float64) + target.azimuth_offset) / azimuths  # [A_t] fraction of a turn
    # Inside the first sample's range there is no data: take the first bin.
    rows = np.maximum(metres / conventions.range_bin - conventions.range_offset, 0.0)
    columns = np.mod(turns * source_azimuths - conventions.azimuth_offset, source_azimuths)
    map_x, map_y = np.meshgrid(columns.astype(np.float32), rows.astype(np.float32), indexing="xy")  # [R_t, A_t]
    image = cv2.remap(_wrapped(polar), map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def scan_agreement(converted: np.ndarray, reference: np.ndarray, radius_px: float | None = None) -> tuple[float, float]:
    """Two uint8 [S, S] scans -> (mean absolute grey difference, Pearson correlation) over the pixels whose centre
    lies within radius_px of the image centre (default S/2: the sensor's disc, not the black corners)."""
    converted, reference = np.asarray(converted, np.float64), np.asarray(reference, np.float64)
    if converted.shape != reference.shape or converted.ndim != 2 or converted.shape[0] != converted.shape[1]:
        raise ValueError(f"need two square scans of one size, got {converted.shape} and {reference.shape}")
    size = converted.shape[0]
    radius = size / 2.0 if radius_px is None else float(radius_px)
    centres = np.arange(size) + 0.5 - size / 2.0
    inside = np.hypot(*np.meshgrid(centres, centres)) < radius  # [S, S]
    a, b = converted[inside], reference[inside]
    return float(np.abs(a - b).mean()), float(np.corrcoef(a, b)[0, 1])


def accepts_polar(input_size: int, resolution: float) -> bool:
    """Polar scans are accepted wherever a full RADIATE scan is: they are converted to one."""
    return RADIATE_SCAN_SIZE in accepted_sizes(input_size, resolution)


@dataclass(frozen=True)
class PolarSource:
    """How a polar-only folder's scans become Cartesian ones: the side and resolution of the converted scan."""

    size: int  # pixels per side
    resolution: float  # metres per pixel

    def load(self, path: Path) -> np.ndarray:
        """Navtech_Polar PNG -> uint8 [size, size] Cartesian scan (RADIATE's conventions)."""
        polar = load_image(path)
        try:
            return polar_to_cartesian(polar, self.size, self.resolution)
        except ValueError as error:
            raise ValueError(f"polar scan {path}: {error}") from error
