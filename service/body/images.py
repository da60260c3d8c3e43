"""Posted radar frames: 8-bit greyscale PNG, a full RADIATE scan, the model's input size, a polar scan in
RADIATE's Navtech_Polar layout or a native scan as Oxford Radar RobotCar and Boreas store them, -> the model's crop.

`decode_frame` is THE decode: every posted image goes through it (on the decode executor), and it ends in
rafd.preprocess, the one torch-free path from a scan to the model input. A polar scan is recognised by its
shape (576 rows of range x 400 columns of azimuth; Cartesian inputs are square, so none has it) and converted
there with rafd.preprocess.polar_to_cartesian to RADIATE's 1152 px Cartesian scan, which then takes the
Cartesian path unchanged. A native scan (one row per azimuth: timestamp, encoder angle, valid flag, then the range
bins; rafd.scans.native) is recognised by its shape too (a few hundred rows, far wider than high) and converted with
rafd.scans.native.to_cartesian the same way. `check_posted_image` is its cheap first half (chunk headers only), run on
the event loop as soon as the body is parsed so a hostile file is refused before it takes a decode slot;
`upload_check` runs the same rules on a multipart upload while it streams in.

What each form is (its shape, the dataset a native width is read as, the sizes a model accepts) is rafd.scans; this
module decodes a posted body and answers every failure with an ApiError.
"""

from __future__ import annotations

import binascii
import logging
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from rafd.geometry import RADIATE_SCAN_SIZE
from rafd.preprocess import model_crop_of_top_rows, polar_to_cartesian
from rafd.scans.cartesian import accepted_sizes
from rafd.scans.native import (
    FLAG_COLUMN,
    SENSOR_SHAPE,
    NativeShape,
    format_for,
    is_native_shape,
    native_format_name,
    parse_native_scan,
)
from rafd.scans.native import to_cartesian as native_to_cartesian
from rafd.scans.polar import RADIATE_POLAR_SHAPE, accepts_polar
from service.body import png
from service.http.errors import ApiError

log = logging.getLogger(__name__)

# Odometry registers this much of the posted scan around the radar (89 m at RADIATE's resolution):
# on the model's small crop alone the static scene is too sparse and registration sometimes locks
# onto vehicles that move with the ego.
ODOMETRY_VIEW_SIZE = 512
DATA_URL_PREFIX = "data:image/png;base64,"

# A posted image: PNG bytes (multipart file) or base64 text of them (JSON field).
PostedImage = bytes | str


@dataclass(frozen=True)
class DecodedFrame:
    covered: np.ndarray  # [C, C] uint8, the square detected over (rafd.runtime.view), centred on the radar
    # Side of the Cartesian scan that polygons and the flow grid are answered in: the posted image, or the
    # RADIATE scan a posted polar or native scan was converted to (1152).
    posted_size: int
    odometry_view: np.ndarray  # [V, V] uint8 centre of that scan that odometry registers
    posted_format: str = "cartesian"  # or "polar" (RADIATE's Navtech_Polar), or "native" (Oxford / Boreas)
    # native scans: (per-azimuth timestamps in UNIX microseconds [A], azimuths in radians clockwise from forward [A])
    sweep: tuple[np.ndarray, np.ndarray] | None = None
    native_format: str | None = None  # native scans: the format read (rafd.scans.native.NATIVE_FORMATS)
    native_range_bin_m: float | None = None  # native scans: metres per range bin used


def strip_data_url(text: str) -> str:
    """A base64 JSON image may carry a `data:image/png;base64,` prefix."""
    if text.startswith("data:"):
        if not text.startswith(DATA_URL_PREFIX):
            raise ApiError("invalid_image", f"a data URL image must start with {DATA_URL_PREFIX!r}")
        return text[len(DATA_URL_PREFIX) :]
    return text


def _source(image: PostedImage) -> png.ByteSource:
    return png.Base64Bytes(strip_data_url(image)) if isinstance(image, str) else png.RawBytes(image)


def _check_size(header: png.PngHeader, input_size: int, resolution: float, native: NativeShape = SENSOR_SHAPE) -> None:
    """422 unless the PNG is an accepted square Cartesian size or (where accepted) a RADIATE polar or a native scan
    of a real sensor's size (`native`): from the header alone, so the inflate and the conversion are bounded before
    any work."""
    sizes = accepted_sizes(input_size, resolution)
    polar = accepts_polar(input_size, resolution)
    polar_shape = (header.height, header.width) == RADIATE_POLAR_SHAPE
    if polar and (polar_shape or is_native_shape(header.width, header.height, native)):
        return
    if header.width != header.height or header.width not in sizes:
        accepted = " or ".join(f"{s}x{s}" for s in sizes)
        if polar:
            bins, azimuths = RADIATE_POLAR_SHAPE
            accepted += (
                f" (Cartesian), or {azimuths}x{bins} (a polar scan: {azimuths} azimuth columns x {bins} range "
                "rows, RADIATE's Navtech_Polar layout), or a native scan "
                f"(Oxford / Boreas: {native.describe()})"
            )
        raise ApiError(
            "unsupported_image_size",
            f"image is {header.width}x{header.height} (width x height); accepted sizes: {accepted}",
        )


def check_posted_image(
    image: PostedImage, input_size: int, resolution: float, native: NativeShape = SENSOR_SHAPE
) -> png.PngLayout:
    """Chunk structure, format and size from the headers alone: 422 before any pixel is decoded."""
    layout = png.read_layout(_source(image))
    _check_size(layout.header, input_size, resolution, native)
    return layout


def upload_check(input_size: int, resolution: float, native: NativeShape = SENSOR_SHAPE) -> Callable[[bytes], None]:
    """A feeder for a PNG file upload as it streams in: refuses by chunk headers, format and size as soon as they
    arrive, so a hostile upload is answered before the rest of its body is received."""
    check = png.StreamingCheck()

    def feed(data: bytes) -> None:
        had_header = check.header is not None
        check.feed(data)
        if not had_header and check.header is not None:
            _check_size(check.header, input_size, resolution, native)

    return feed


def decode_frame(
    image: PostedImage,
    input_size: int,
    resolution: float,
    native: NativeShape = SENSOR_SHAPE,
    range_bin_m: float | None = None,
    covered: Callable[[int], int] | None = None,
) -> DecodedFrame:
    """A posted PNG (bytes, or base64 text; Cartesian, polar or native) -> the uint8 square it is detected over (the
    whole scan; `covered`: the side of that square, centred on the radar, for a Cartesian scan of that side, e.g.
    within a range: rafd.runtime.view) and odometry's view; 422 naming what was expected. `range_bin_m` (the request's
    range_resolution_m): a native scan's metres per range bin, in place of its format's; 422 for any other scan. No
    input gives anything else: a failure of the decoding libraries on a posted file is that file's fault (422
    `invalid_image`, logged as a warning), never a 500."""
    try:
        return _decode_frame(image, input_size, resolution, native, range_bin_m, covered)
    except ApiError:
        raise
    except Exception as exc:
        log.warning("decoding a posted image failed: %s: %s", type(exc).__name__, exc)
        raise ApiError("invalid_image", f"the image could not be decoded ({type(exc).__name__})") from exc


def _decode_frame(
    image: PostedImage,
    input_size: int,
    resolution: float,
    native: NativeShape,
    range_bin_m: float | None,
    covered: Callable[[int], int] | None,
) -> DecodedFrame:
    layout = check_posted_image(image, input_size, resolution, native)
    if range_bin_m is not None and layout.header.width == layout.header.height:
        raise ApiError("validation_error", "range_resolution_m applies to native scans only; this image is square")
    if isinstance(image, str):
        try:
            data = png.a2b_base64_strict(strip_data_url(image))
        except (binascii.Error, ValueError) as exc:
            raise ApiError("invalid_image", f"field 'image' is not valid base64: {exc}") from exc
    else:
        data = image
    header = layout.header
    square = header.width == header.height
    cartesian = header.width if square else RADIATE_SCAN_SIZE  # the side of the Cartesian scan it is or becomes
    side = cartesian if covered is None else covered(cartesian)
    # The square read: the covered one and odometry's view around the radar (a square scan is read only down to its
    # last row: the rows below are never unfiltered; a polar or native scan is converted only that far).
    read = max(side, min(cartesian, ODOMETRY_VIEW_SIZE))
    rows = (header.height + read) // 2 if square else header.height
    decoded = cv2.imdecode(np.frombuffer(png.decoder_png(data, layout, rows), np.uint8), cv2.IMREAD_UNCHANGED)
    if decoded is None:
        raise ApiError("invalid_image", "the PNG could not be decoded (corrupt image data)")
    if decoded.ndim != 2 or decoded.dtype != np.uint8:  # the header said 8-bit greyscale: a decoder mismatch
        raise ApiError("unsupported_image_format", f"decoded {decoded.dtype} {decoded.shape}; expected 8-bit grey")
    posted_format = "cartesian"
    sweep = fmt = None
    width = decoded.shape[1]
    if decoded.shape == RADIATE_POLAR_SHAPE:  # the size check let it through: polar scans are accepted here
        if range_bin_m is not None:
            raise ApiError(
                "validation_error", "range_resolution_m applies to native scans only; this is a RADIATE polar scan"
            )
        width, posted_format = RADIATE_SCAN_SIZE, "polar"
        decoded = polar_to_cartesian(decoded, read)  # [576, 400] -> [read, read] uint8, the same pixels as the whole
    elif not square:  # a native scan (the size check let only these through)
        try:
            # Named by its width and column 10 (a Doppler-mode chirp column is no valid flag: rafd.scans.native); the
            # request's range bin, when given, replaces the named format's (the sensor knows it, the width guesses).
            name = native_format_name(decoded.shape[1], decoded[:, FLAG_COLUMN])
            timestamp_us = int(np.ascontiguousarray(decoded[0, :8]).view("<i8")[0])
            fmt = format_for(name, timestamp_us).with_range_bin(range_bin_m)
            scan = parse_native_scan(decoded, fmt)
        except ValueError as exc:
            raise ApiError("invalid_image", f"the native scan's header columns do not read as one: {exc}") from exc
        width, posted_format = RADIATE_SCAN_SIZE, "native"
        decoded = native_to_cartesian(scan, read)  # [A, 11 + R] -> [read, read] uint8
        sweep = (scan.timestamps_us, scan.azimuths)
    return DecodedFrame(
        covered=model_crop_of_top_rows(decoded, side),
        posted_size=width,
        odometry_view=model_crop_of_top_rows(decoded, min(width, ODOMETRY_VIEW_SIZE)),
        posted_format=posted_format,
        sweep=sweep,
        native_format=None if fmt is None else fmt.name,
        native_range_bin_m=None if fmt is None else fmt.range_bin_m,
    )
