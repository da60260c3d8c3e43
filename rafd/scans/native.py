"""Navtech scans in the sensor's own polar layout, as the Oxford Radar RobotCar and Boreas datasets store them, and
their conversion to RADIATE's Cartesian grid (torch-free; part of the one preprocessing path, rafd.preprocess).

One PNG per scan, 8-bit grey, one row per azimuth (400 per turn):
    columns 0-7    the azimuth's timestamp, int64 UNIX microseconds, little-endian bytes
    columns 8-9    the encoder angle, uint16 (5600 counts per turn)
    column 10      valid flag (255: measured; else interpolated by the dataset from its neighbours); in a
                   Navtech RAS6's Doppler mode (Boreas-RT) the up/down chirp of the azimuth instead (0 / 255
                   alternating), which says nothing about validity (NativeFormat.flag_column)
    columns 11-    the range bins, power as 8-bit grey; bin i covers [i, i + 1) bin sizes from the radar (sampled at
                   its centre, as the datasets' SDKs convert them)

Conventions, established on the 13 real Oxford scans of `oxford_radar_sample` (docs/data.md "Native polar scans";
tests/rafd/scans/test_native.py checks them on the sample): the encoder angle counts CLOCKWISE seen from above from the
vehicle's forward direction (angle 0 = straight ahead = image up, a quarter turn = right), the radar sits at the centre
of the converted image, and the azimuths are swept in row order (timestamps increase with the encoder angle): the
only reading under which radar odometry between converted scans agrees with the dataset's ground truth in sign.

Formats (NATIVE_FORMATS, overridable by passing a NativeFormat): the range bin size per dataset and what column 10
holds; the number of range bins and azimuths is read from the PNG itself. A scan that comes without its dataset's name
(a posted one) is read by its width and its column 10 (native_format_name: a column alternating 0 / 255 from azimuth to
azimuth is Boreas-RT's chirp flag); a caller that knows the range bin size (a ROS 2 bag's configuration message, a
request's `range_resolution_m`) passes it (with_range_bin). The sizes accepted are a real sensor's (NativeShape),
checked from the PNG header.

Reading: a native folder's scans (rafd.data.native_folder) load through `NativeSource`, which converts each PNG on
load.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from rafd.geometry import RADIATE_RESOLUTION, RADIATE_SCAN_SIZE
from rafd.scans.cartesian import load_image
from rafd.scans.polar import RADIATE_RANGE_BINS, PolarConventions, polar_to_cartesian

HEADER_COLUMNS = 11  # 8 timestamp bytes + 2 encoder bytes + 1 flag (valid, or chirp in Doppler mode)
FLAG_COLUMN = 10
RADIATE_MAX_RANGE_M = RADIATE_RANGE_BINS * RADIATE_RESOLUTION  # 100 m: RADIATE's scans end there
ENCODER_COUNTS = 5600  # encoder counts per turn (Navtech CTS350-X and CIR304-H)
# What a real sensor's header holds (parse_native_scan refuses the rest, naming the rule): azimuth times in UNIX
# microseconds from 1970 to 2100 (the service's timestamp range), one sweep turning at 1-10 Hz (the documented sensors
# turn at 4 Hz: 0.248-0.253 s on the Oxford sample), and at least half of the azimuths measured (valid flag 255).
MAX_TIMESTAMP_US = 4_102_444_800_000_000  # 2100-01-01T00:00:00Z
SWEEP_PERIOD_S = (0.1, 1.0)
MIN_VALID_FRACTION = 0.5


@dataclass(frozen=True)
class NativeFormat:
    """What the PNG does not say about a dataset's scans."""

    name: str
    range_bin_m: float  # metres per range bin
    encoder_counts: int = ENCODER_COUNTS
    description: str = ""
    # What column 10 holds: "valid" (Oxford, Boreas: 255 = measured) or "chirp" (a Navtech RAS6 in Doppler mode: the
    # azimuth's up/down chirp, 0 / 255 alternating; every azimuth is measured).
    flag_column: Literal["valid", "chirp"] = "valid"

    def __post_init__(self) -> None:
        if not (math.isfinite(self.range_bin_m) and self.range_bin_m > 0):
            raise ValueError(f"range_bin_m must be a positive number of metres, got {self.range_bin_m}")
        if self.encoder_counts < 1:
            raise ValueError(f"encoder_counts must be >= 1, got {self.encoder_counts}")
        if self.flag_column not in ("valid", "chirp"):
            raise ValueError(f"flag_column must be 'valid' or 'chirp', got {self.flag_column!r}")

    def with_range_bin(self, range_bin_m: float | None) -> NativeFormat:
        """This format with the range bin size a caller knows (a bag's configuration, a request's field); itself
        when None."""
        return self if range_bin_m is None else replace(self, range_bin_m=float(range_bin_m))


OXFORD_RANGE_BINS = 3768  # range bins of an Oxford Radar RobotCar scan (its CTS350-X: 163 m)
# The documented table. Boreas changed its radar's range resolution on 2021-09-21 (pyboreas' upgrade time
# 1632182400): scans before it use `boreas`, after it `boreas-2021`.
NATIVE_FORMATS: dict[str, NativeFormat] = {
    fmt.name: fmt
    for fmt in (
        NativeFormat(
            "oxford", 0.0432, description=f"Oxford Radar RobotCar, Navtech CTS350-X: {OXFORD_RANGE_BINS} bins (163 m)"
        ),
        NativeFormat("boreas", 0.0596, description="Boreas, Navtech CIR304-H, until 2021-09-21"),
        NativeFormat("boreas-2021", 0.04381, description="Boreas, Navtech CIR304-H, from 2021-09-21"),
        NativeFormat(
            "boreas-rt",
            0.04381,
            description="Boreas-RT, Navtech RAS6 in Doppler mode: column 10 is the up/down chirp flag, not validity",
            flag_column="chirp",
        ),
    )
}
BOREAS_UPGRADE_US = 1_632_182_400_000_000  # pyboreas' upgrade time, UNIX microseconds


def format_for(name: str | NativeFormat, timestamp_us: int | None = None) -> NativeFormat:
    """A format by name ("oxford", "boreas", "boreas-2021"; "boreas" picks by the scan's time when it is given)."""
    if isinstance(name, NativeFormat):
        return name
    if name == "boreas" and timestamp_us is not None and timestamp_us > BOREAS_UPGRADE_US:
        name = "boreas-2021"
    if name not in NATIVE_FORMATS:
        raise ValueError(f"unknown native scan format {name!r}; known: {sorted(NATIVE_FORMATS)}")
    return NATIVE_FORMATS[name]


# native_format_name's rule, in words (the service's GET /model says it).
NATIVE_FORMAT_RULE = (
    "column 10 alternating 0 / 255 from azimuth to azimuth (a Navtech RAS6's up/down chirp flag in Doppler mode): "
    f"boreas-rt; else {OXFORD_RANGE_BINS} range bins: oxford; any other number: boreas (boreas-2021 after its sensor "
    "upgrade, by the scan's timestamp). A request's range_resolution_m replaces the format's range bin size"
)


def is_chirp_column(flags: np.ndarray) -> bool:
    """Whether a scan's column 10 is a Doppler-mode chirp flag: 0 and 255 alternating from each azimuth to the next.
    An Oxford-style valid flag is 255 on (nearly) every azimuth: alternation over a whole sweep is no valid flag."""
    flags = np.asarray(flags)
    if flags.size < 2 or not np.all((flags == 0) | (flags == 255)):
        return False
    return bool(np.all(flags[1:] != flags[:-1]))


def native_format_name(width: int, flags: np.ndarray | None = None) -> str:
    """The dataset a native scan without a name (a posted one) is read as: Boreas-RT when its column 10 (`flags`)
    alternates like a chirp flag, else by its PNG width: Oxford's 3768 range bins, else Boreas' (format_for then
    picks boreas-2021 by the scan's time)."""
    if flags is not None and is_chirp_column(flags):
        return "boreas-rt"
    return "oxford" if width - HEADER_COLUMNS == OXFORD_RANGE_BINS else "boreas"


@dataclass(frozen=True)
class NativeScan:
    """One native scan, decoded."""

    timestamps_us: np.ndarray  # int64 [A] UNIX microseconds of each azimuth
    encoder: np.ndarray  # int64 [A] encoder angle of each azimuth (counts)
    valid: np.ndarray  # bool [A] (all true where column 10 is a chirp flag)
    power: np.ndarray  # uint8 [A, R]
    fmt: NativeFormat

    @property
    def timestamp_us(self) -> int:
        """The scan's timestamp: its first azimuth's (the datasets name each file after it)."""
        return int(self.timestamps_us[0])

    @property
    def azimuths(self) -> np.ndarray:
        """float64 [A] radians clockwise from forward, unwrapped so that they increase through the sweep."""
        turns = self.encoder.astype(np.float64) / self.fmt.encoder_counts
        return np.unwrap(turns * 2.0 * np.pi)

    @property
    def range_bins(self) -> int:
        return int(self.power.shape[1])


@dataclass(frozen=True)
class NativeShape:
    """The native scan sizes accepted: azimuth rows and range-bin columns (after the 11 header columns). The defaults
    are the documented sensors' (Oxford's CTS350-X: 400 azimuths x 3768 bins; Boreas' CIR304-H: 400 azimuths, at most
    6848 bins, its 300 m at 0.04381 m), so what a PNG's header declares bounds the inflate and the conversion before
    any work: an all-zero 400 x 400,000 PNG is 389 KB and would inflate to 160 MB."""

    min_azimuths: int = 100
    max_azimuths: int = 400
    max_range_bins: int = 6848

    def accepts(self, width: int, height: int) -> bool:
        bins = width - HEADER_COLUMNS
        return self.min_azimuths <= height <= self.max_azimuths and 2 * height < bins <= self.max_range_bins

    def rows_rule(self) -> str:
        return f"one per azimuth, {self.min_azimuths}-{self.max_azimuths}"

    def columns_rule(self) -> str:
        return (
            f"{HEADER_COLUMNS} header columns (timestamp, encoder angle, valid flag) + more than twice the rows and at "
            f"most {self.max_range_bins} range bins"
        )

    def describe(self) -> str:
        """The rule in one line (error messages); GET /model gives its parts (rows_rule, columns_rule)."""
        return f"rows {self.rows_rule()}; columns {self.columns_rule()}"


SENSOR_SHAPE = NativeShape()  # the documented sensors' sizes


def is_native_shape(width: int, height: int, shape: NativeShape = SENSOR_SHAPE) -> bool:
    """Whether a PNG of this size can be a native scan: some hundreds of azimuth rows, far more range columns, within
    the sensors' sizes (`shape`)."""
    return shape.accepts(width, height)


def check_header(timestamps: np.ndarray, encoder: np.ndarray, valid: np.ndarray, fmt: NativeFormat) -> None:
    """ValueError naming the rule when a scan's header columns are not one sweep of a real sensor: azimuth times in
    range and strictly increasing, spanning about one rotation (SWEEP_PERIOD_S); encoder angles within the encoder's
    counts and strictly increasing over at most one turn (wrapping once through 0); at least MIN_VALID_FRACTION of
    the azimuths measured. Degenerate headers (all angles equal, reversed, random or two turns; times all equal,
    negative or at INT64_MAX) otherwise bend the conversion and the motion compensation of every later frame."""
    if np.any(timestamps < 0) or np.any(timestamps > MAX_TIMESTAMP_US):
        raise ValueError(
            "rule azimuth_time_range: the azimuth timestamps must be UNIX microseconds from 1970 to 2100, "
            f"got {int(timestamps.min())} to {int(timestamps.max())}"
        )
    steps = np.diff(timestamps)  # no overflow: both ends are within [0, MAX_TIMESTAMP_US]
    if np.any(steps < 0):
        raise ValueError(
            "rule azimuth_time_increasing: the native scan's azimuth timestamps decrease (not a native scan, or a "
            "corrupt one)"
        )
    if np.any(steps == 0):
        raise ValueError("rule azimuth_time_increasing: two azimuths share a timestamp; they must increase strictly")
    counts = fmt.encoder_counts
    if np.any(encoder >= counts):
        raise ValueError(
            f"rule encoder_range: encoder angles reach {int(encoder.max())}, beyond {counts} counts per turn"
        )
    turned = np.diff(encoder) % counts  # counts advanced from each azimuth to the next, wrapping through 0
    if np.any(turned == 0) or int(turned.sum()) >= counts:
        raise ValueError(
            "rule encoder_one_turn: the encoder angles must increase strictly over less than one turn "
            f"({counts} counts, wrapping through 0 at most once); these advance {int(turned.sum())} counts"
            + (" with repeated angles" if np.any(turned == 0) else "")
        )
    period_s = float(timestamps[-1] - timestamps[0]) * counts / float(turned.sum()) / 1e6
    if not SWEEP_PERIOD_S[0] <= period_s <= SWEEP_PERIOD_S[1]:
        raise ValueError(
            f"rule sweep_period: the azimuth times imply one rotation in {period_s:.4g} s; a radar's sweep turns in "
            f"{SWEEP_PERIOD_S[0]:g}-{SWEEP_PERIOD_S[1]:g} s (Oxford and Boreas: 0.25 s)"
        )
    if valid.mean() < MIN_VALID_FRACTION:
        raise ValueError(
            f"rule valid_azimuths: {int(valid.sum())} of {valid.size} azimuths are measured (valid flag 255); at "
            f"least {MIN_VALID_FRACTION:.0%} must be"
        )


def parse_native_scan(image: np.ndarray, fmt: str | NativeFormat = "oxford") -> NativeScan:
    """uint8 [A, 11 + R] native PNG pixels -> NativeScan; ValueError when the rows do not read as a scan. Column 10
    is the valid flag, or, in a format whose flag_column is "chirp", ignored (every azimuth measured)."""
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim != 2 or image.shape[1] <= HEADER_COLUMNS:
        raise ValueError(f"a native scan is uint8 [azimuths, 11 + range bins], got {image.dtype} {image.shape}")
    header = np.ascontiguousarray(image[:, :HEADER_COLUMNS])
    timestamps = header[:, :8].copy().view("<i8").ravel().astype(np.int64)
    encoder = header[:, 8:10].copy().view("<u2").ravel().astype(np.int64)
    fmt = format_for(fmt, int(timestamps[0]))
    flags = header[:, FLAG_COLUMN]
    valid = np.ones(len(flags), bool) if fmt.flag_column == "chirp" else flags == 255
    check_header(timestamps, encoder, valid, fmt)
    return NativeScan(timestamps, encoder, valid, np.ascontiguousarray(image[:, HEADER_COLUMNS:]), fmt)


def read_native_scan(path: str | Path, fmt: str | NativeFormat = "oxford") -> NativeScan:
    """A native scan PNG file -> NativeScan (FileNotFoundError / ValueError naming the file)."""
    image = load_image(path, cv2.IMREAD_UNCHANGED, "native radar scan")
    try:
        return parse_native_scan(image, fmt)
    except ValueError as error:
        raise ValueError(f"native radar scan {path}: {error}") from error


def to_polar(
    scan: NativeScan, range_bin: float = RADIATE_RESOLUTION, max_range_m: float | None = None
) -> tuple[np.ndarray, PolarConventions]:
    """A native scan -> (float32 polar [range rows, azimuths] on uniform azimuths, its PolarConventions).

    Range is averaged down to bins of about `range_bin` metres (area averaging: no aliasing of the fine bins, e.g. 4.02
    Oxford bins per RADIATE bin); rows beyond `max_range_m` are dropped. Azimuths are resampled onto a uniform grid
    from the encoder angles when they are not already uniform (Boreas' early scans wobble)."""
    power = scan.power.astype(np.float32)  # [A, R]
    azimuths, bins = power.shape
    native_bin = scan.fmt.range_bin_m
    rows = max(1, int(round(bins * native_bin / range_bin)))
    polar = cv2.resize(power.T, (azimuths, rows), interpolation=cv2.INTER_AREA)  # [rows, A]
    bin_m = bins * native_bin / rows  # exact size of an averaged bin
    if max_range_m is not None:
        polar = polar[: min(rows, int(math.ceil(max_range_m / bin_m)) + 1)]
    # azimuth of row j in steps of a uniform grid of `azimuths` per turn, from the encoder
    steps = scan.azimuths / (2.0 * np.pi) * azimuths  # [A], increasing
    offset = float(steps[0])
    valid = np.asarray(scan.valid, bool)
    # Not uniform, or some azimuths not measured (valid flag not 255): resample each range row from the measured
    # azimuths only, so an unmeasured azimuth's bins never reach the converted scan.
    if not valid.all() or np.max(np.abs(steps - (offset + np.arange(azimuths)))) > 1e-3:
        target = offset + np.arange(azimuths, dtype=np.float64)
        kept = steps[valid] if valid.any() else steps
        source = polar[:, valid] if valid.any() else polar
        wrapped_steps = np.concatenate([kept - azimuths, kept, kept + azimuths])
        polar = np.stack([np.interp(target, wrapped_steps, np.tile(row, 3)) for row in source]).astype(np.float32)
    offset = offset % azimuths
    conventions = PolarConventions(azimuth_offset=offset, range_offset=0.5, range_bin=bin_m, centre_offset=(0.0, 0.0))
    return polar, conventions


def to_cartesian(
    scan: NativeScan,
    size: int = RADIATE_SCAN_SIZE,
    resolution: float = RADIATE_RESOLUTION,
    max_range_m: float = RADIATE_MAX_RANGE_M,
) -> np.ndarray:
    """A native scan -> uint8 [size, size] Cartesian scan on RADIATE's grid (radar at the centre, x right, y forward
    = image up, `resolution` metres per pixel), so it reads like a RADIATE scan everywhere in the project: black
    beyond `max_range_m` (RADIATE's 100 m disc; the Oxford radar reaches 163 m)."""
    polar, conventions = to_polar(scan, resolution, max_range_m=max_range_m)
    rows = int(math.floor(max_range_m / conventions.range_bin))
    return polar_to_cartesian(polar[:rows], size, resolution, conventions)


@dataclass(frozen=True)
class NativeSource:
    """How a native folder's scans become Cartesian ones: the dataset's format, the side and resolution."""

    fmt: NativeFormat
    size: int = RADIATE_SCAN_SIZE
    resolution: float = RADIATE_RESOLUTION

    def load(self, path: Path) -> np.ndarray:
        """Native scan PNG -> uint8 [size, size] Cartesian scan (RADIATE's grid)."""
        return to_cartesian(read_native_scan(path, self.fmt), self.size, self.resolution)
