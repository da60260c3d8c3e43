"""A radar scan message -> a native scan (rafd.scans.native's layout: one row per azimuth, its time and encoder angle
in the 11 header columns, then the range bins), the form the service's native path reads (it de-skews by the
azimuths' times), or a RADIATE polar scan posted as it is.

Messages (decoded by rosbags; attributes as in their .msg definitions):
- navtech_msgs/RadarBScanMsg: `b_scan_img` (mono8 / 8UC1, one row per azimuth, one column per range bin),
  `encoder_values` (one per row), `timestamps` (UNIX ns, one per row). Navtech's driver rotates the image rows by the
  configuration's azimuth_offset but not the two arrays: the rows are turned back so that each meets its own angle
  and time. The scan's time is its image's header stamp.
- sensor_msgs/Image and sensor_msgs/CompressedImage (PNG): a native scan with its header columns (as drivers that
  publish Oxford / Boreas-style polar images write them, and as the datasets store them), a RADIATE polar scan
  (576 range rows x 400 azimuth columns), or a plain B-scan without header columns (one row per azimuth): its rows
  are taken as evenly spaced in angle and time over one rotation (the configuration's, else `rotation_hz`) centred on
  the header stamp, the first row at encoder angle 0.

The range bin comes from the configuration (RadarConfigurationMsg's bin_size: the radar's unit, tenths of a
millimetre, or metres where a driver wrote metres, told apart by size) or from the caller's flags (RadarGeometry);
without either, a native scan goes without one and the service reads it by its width. Encoder angles are rescaled
to the native layout's 5600 counts per turn when the radar counts otherwise (a RAS6: 5595). A B-scan carries no
valid flag: column 10 is 255 (measured) on every row.

Every failure is a ScanError naming what is wrong; sizes are checked against a real sensor's (NativeShape) before
anything is allocated from them.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from rafd.scans.native import (
    ENCODER_COUNTS,
    HEADER_COLUMNS,
    SENSOR_SHAPE,
    NativeShape,
    check_header,
    format_for,
    native_format_name,
)
from rafd.scans.polar import RADIATE_AZIMUTHS, RADIATE_RANGE_BINS

GREY_ENCODINGS = ("mono8", "8UC1")
DEFAULT_ROTATION_HZ = 4.0  # Navtech CTS350-X, CIR304-H and RAS6 turn at 4 Hz
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


class ScanError(ValueError):
    """A scan message that does not read as a radar scan (the reader adds the topic and message)."""


@dataclass(frozen=True)
class RadarGeometry:
    """What a scan's message does not say: from the bag's RadarConfigurationMsg or the caller's flags."""

    range_bin_m: float | None = None
    azimuth_samples: int | None = None
    range_in_bins: int | None = None
    encoder_size: int = ENCODER_COUNTS
    azimuth_offset: int = 0
    rotation_hz: float = DEFAULT_ROTATION_HZ
    source: str = "flags"  # "configuration <topic>" or "flags"


@dataclass(frozen=True)
class BagScan:
    """One scan read from a bag: `layout` "native" (uint8 [A, 11 + R], posted with `range_bin_m` when known) or
    "polar" (RADIATE's uint8 [576, 400], posted as it is)."""

    stamp_ns: int  # the scan's time: its header stamp (UNIX ns)
    pixels: np.ndarray
    layout: str
    range_bin_m: float | None
    frame_id: str = ""


def bin_size_metres(value: float) -> float:
    """A configuration's bin_size -> metres: the radar's own unit is a tenth of a millimetre (438 for 0.0438 m); a
    value below 1 is already metres (some drivers convert)."""
    value = float(value)
    if not np.isfinite(value) or value <= 0:
        raise ScanError(f"the configuration's bin_size is {value}; a range bin has a positive size")
    return value / 10_000.0 if value >= 1.0 else value


def _big_endian(data: Any, field: str) -> float:
    """An older driver's byte-array field (network order) -> its value: 1, 2, 4 or 8 bytes an unsigned integer, or 8
    bytes a double when it does not read as a plausible integer (the bin size was written either way)."""
    raw = bytes(np.asarray(data, dtype=np.uint8))
    if len(raw) in (1, 2, 4):
        return float(int.from_bytes(raw, "big"))
    if len(raw) == 8:
        integer = int.from_bytes(raw, "big")
        if integer < 2**32:
            return float(integer)
        return float(struct.unpack(">d", raw)[0])
    raise ScanError(f"the configuration's {field} is {len(raw)} bytes; expected 1, 2, 4 or 8")


def geometry_of(
    configuration: Any, source: str, legacy: bool, rotation_hz: float = DEFAULT_ROTATION_HZ
) -> RadarGeometry:
    """A decoded RadarConfigurationMsg (typed fields, or `legacy` byte arrays) -> RadarGeometry."""

    def field(name: str) -> float:
        value = getattr(configuration, name)
        return _big_endian(value, name) if legacy else float(value)

    azimuths, encoder, bins = int(field("azimuth_samples")), int(field("encoder_size")), int(field("range_in_bins"))
    if azimuths < 1 or encoder < azimuths or bins < 1:
        raise ScanError(
            f"the configuration says {azimuths} azimuths, {encoder} encoder counts and {bins} range bins: not a radar"
        )
    offset = 0 if legacy or not hasattr(configuration, "azimuth_offset") else int(configuration.azimuth_offset)
    rate = field("expected_rotation_rate")
    return RadarGeometry(
        range_bin_m=bin_size_metres(field("bin_size")),
        azimuth_samples=azimuths,
        range_in_bins=bins,
        encoder_size=encoder,
        azimuth_offset=offset % azimuths,
        rotation_hz=rate if 0.1 <= rate <= 10.0 else rotation_hz,
        source=source,
    )


def stamp_ns(header: Any) -> int:
    """A std_msgs/Header's stamp -> UNIX nanoseconds."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def image_pixels(image: Any, shape: NativeShape = SENSOR_SHAPE) -> np.ndarray:
    """A sensor_msgs/Image (8-bit grey) -> uint8 [height, width], its rows read through `step`; ScanError when its
    encoding, sizes or data disagree."""
    encoding = str(image.encoding)
    if encoding not in GREY_ENCODINGS:
        raise ScanError(f"image encoding {encoding!r}; a radar scan is 8-bit grey ({' or '.join(GREY_ENCODINGS)})")
    height, width, step = int(image.height), int(image.width), int(image.step)
    if not _plausible(width, height, shape):
        raise ScanError(f"image of {width} x {height} (width x height) is no radar scan: {shape.describe()}")
    data = np.asarray(image.data, dtype=np.uint8).reshape(-1)
    if step < width or data.size != step * height:
        raise ScanError(f"image data of {data.size} bytes for {height} rows of step {step} and width {width}")
    return np.ascontiguousarray(data.reshape(height, step)[:, :width])


def _plausible(width: int, height: int, shape: NativeShape) -> bool:
    """A native scan with header columns, a RADIATE polar scan, or a plain B-scan (rows = azimuths)."""
    plain = shape.accepts(width + HEADER_COLUMNS, height)
    return shape.accepts(width, height) or (height, width) == (RADIATE_RANGE_BINS, RADIATE_AZIMUTHS) or plain


def png_pixels(data: bytes, shape: NativeShape = SENSOR_SHAPE) -> np.ndarray:
    """A CompressedImage's PNG -> uint8 [height, width], its size checked from the PNG header before it is
    inflated (a small file must not inflate to gigabytes)."""
    if len(data) < 33 or not data.startswith(PNG_SIGNATURE) or data[12:16] != b"IHDR":
        raise ScanError("compressed image is not a PNG (no PNG signature and IHDR chunk)")
    width, height, depth, colour = struct.unpack(">IIBB", data[16:26])
    if depth != 8 or colour != 0:
        raise ScanError(f"PNG of bit depth {depth} and colour type {colour}; a radar scan is 8-bit grey (type 0)")
    if not _plausible(width, height, shape):
        raise ScanError(f"PNG of {width} x {height} (width x height) is no radar scan: {shape.describe()}")
    pixels = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if pixels is None or pixels.shape != (height, width) or pixels.dtype != np.uint8:
        raise ScanError("PNG data is corrupt (it does not decode to the size its header says)")
    return pixels


def native_header(timestamps_us: np.ndarray, encoder: np.ndarray) -> np.ndarray:
    """uint8 [A, 11]: the native layout's header columns (times, encoder angles, flag 255 = measured)."""
    rows = len(timestamps_us)
    header = np.empty((rows, HEADER_COLUMNS), np.uint8)
    header[:, :8] = np.asarray(timestamps_us, np.int64).astype("<i8").view(np.uint8).reshape(rows, 8)
    header[:, 8:10] = np.asarray(encoder, np.int64).astype("<u2").view(np.uint8).reshape(rows, 2)
    header[:, 10] = 255
    return header


def _counts_of(encoder: np.ndarray, encoder_size: int) -> np.ndarray:
    """Encoder angles in a radar's counts -> the native layout's ENCODER_COUNTS per turn."""
    if encoder_size == ENCODER_COUNTS:
        return encoder.astype(np.int64)
    return np.round(encoder.astype(np.float64) * ENCODER_COUNTS / encoder_size).astype(np.int64) % ENCODER_COUNTS


def _check_geometry(pixels: np.ndarray, geometry: RadarGeometry | None) -> None:
    if geometry is None or geometry.azimuth_samples is None:
        return
    azimuths, bins = pixels.shape
    if (azimuths, bins) != (geometry.azimuth_samples, geometry.range_in_bins):
        raise ScanError(
            f"the scan is {azimuths} azimuths x {bins} range bins but its configuration ({geometry.source}) says "
            f"{geometry.azimuth_samples} x {geometry.range_in_bins}"
        )


def _checked(native: np.ndarray, range_bin_m: float | None) -> np.ndarray:
    """The native scan's header checked as the service checks it (one sweep of a real sensor)."""
    timestamps = np.ascontiguousarray(native[:, :8]).view("<i8").ravel()
    encoder = np.ascontiguousarray(native[:, 8:10]).view("<u2").ravel().astype(np.int64)
    fmt = format_for(native_format_name(native.shape[1], native[:, 10]), int(timestamps[0]))
    try:
        check_header(timestamps.astype(np.int64), encoder, np.ones(len(encoder), bool), fmt.with_range_bin(range_bin_m))
    except ValueError as error:
        raise ScanError(f"its azimuth times and angles are not one sweep of a radar: {error}") from error
    return native


def from_b_scan(message: Any, geometry: RadarGeometry | None) -> BagScan:
    """navtech_msgs/RadarBScanMsg -> BagScan (native layout)."""
    pixels = image_pixels(message.b_scan_img, SENSOR_SHAPE)
    azimuths, bins = pixels.shape
    if not SENSOR_SHAPE.accepts(bins + HEADER_COLUMNS, azimuths):
        raise ScanError(f"B-scan of {azimuths} azimuths x {bins} range bins: {SENSOR_SHAPE.describe()}")
    encoder = np.asarray(message.encoder_values, dtype=np.int64).reshape(-1)
    times_ns = np.asarray(message.timestamps, dtype=np.uint64).reshape(-1)
    if encoder.size != azimuths or times_ns.size != azimuths:
        raise ScanError(f"{encoder.size} encoder values and {times_ns.size} timestamps for {azimuths} image rows")
    _check_geometry(pixels, geometry)
    if geometry is not None and geometry.azimuth_offset:
        pixels = np.roll(pixels, -geometry.azimuth_offset, axis=0)  # the driver turned the rows, not the arrays
    encoder_size = geometry.encoder_size if geometry is not None else ENCODER_COUNTS
    if np.any(encoder >= encoder_size):
        raise ScanError(f"encoder values reach {int(encoder.max())}, beyond {encoder_size} counts per turn")
    times_us = (times_ns // np.uint64(1000)).astype(np.int64)
    native = np.concatenate([native_header(times_us, _counts_of(encoder, encoder_size)), pixels], axis=1)
    range_bin = None if geometry is None else geometry.range_bin_m
    image = message.b_scan_img
    return BagScan(stamp_ns(image.header), _checked(native, range_bin), "native", range_bin, str(image.header.frame_id))


def _plain_b_scan(pixels: np.ndarray, stamp: int, geometry: RadarGeometry | None) -> np.ndarray:
    """A B-scan without header columns: rows evenly spaced over one rotation centred on `stamp`."""
    azimuths = pixels.shape[0]
    _check_geometry(pixels, geometry)
    geometry = geometry or RadarGeometry()
    if geometry.azimuth_offset:
        pixels = np.roll(pixels, -geometry.azimuth_offset, axis=0)
    period_us = 1e6 / geometry.rotation_hz
    rows = np.arange(azimuths, dtype=np.float64)
    times_us = np.round(stamp / 1000.0 + (rows - (azimuths - 1) / 2.0) * period_us / azimuths).astype(np.int64)
    encoder = np.round(rows * ENCODER_COUNTS / azimuths).astype(np.int64)
    return np.concatenate([native_header(times_us, encoder), pixels], axis=1)


def from_image_pixels(pixels: np.ndarray, stamp: int, geometry: RadarGeometry | None, frame_id: str) -> BagScan:
    """An image's pixels (from Image or CompressedImage) -> BagScan: native with header columns, RADIATE polar, or a
    plain B-scan."""
    range_bin = None if geometry is None else geometry.range_bin_m
    height, width = pixels.shape
    if (height, width) == (RADIATE_RANGE_BINS, RADIATE_AZIMUTHS):
        return BagScan(stamp, pixels, "polar", None, frame_id)
    if SENSOR_SHAPE.accepts(width, height):  # header columns, if they read as one sweep
        try:
            return BagScan(stamp, _checked(pixels, range_bin), "native", range_bin, frame_id)
        except ScanError:
            if not SENSOR_SHAPE.accepts(width + HEADER_COLUMNS, height):
                raise
    return BagScan(stamp, _checked(_plain_b_scan(pixels, stamp, geometry), range_bin), "native", range_bin, frame_id)


def from_image(message: Any, geometry: RadarGeometry | None) -> BagScan:
    """sensor_msgs/Image -> BagScan."""
    return from_image_pixels(
        image_pixels(message, SENSOR_SHAPE), stamp_ns(message.header), geometry, str(message.header.frame_id)
    )


def from_compressed_image(message: Any, geometry: RadarGeometry | None) -> BagScan:
    """sensor_msgs/CompressedImage (PNG) -> BagScan."""
    if "png" not in str(message.format).lower():
        raise ScanError(f"compressed image format {str(message.format)!r}; only PNG keeps a radar scan's values")
    pixels = png_pixels(bytes(np.asarray(message.data, dtype=np.uint8)), SENSOR_SHAPE)
    return from_image_pixels(pixels, stamp_ns(message.header), geometry, str(message.header.frame_id))
