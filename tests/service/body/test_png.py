"""The one bounded inflate (service/body/png.py): the decoder gets the inflated rows stored, only as many as are read,
and the pixels are those of a plain decode; what libpng would have refused in the rows it is no longer given (a
bad filter byte, a bad CRC) is still refused."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from rafd.preprocess import model_crop
from rafd.runtime.view import View
from service.body import png
from service.body.images import ODOMETRY_VIEW_SIZE, decode_frame
from service.http.errors import ApiError
from tests.utils.png_testing import grey_png

RESOLUTION = 0.173611  # RADIATE's: a full 1152 px scan is accepted beside the model's crop


def chunks_of(data: bytes) -> dict[bytes, bytes]:
    """type -> data of a PNG's chunks (the last of each type)."""
    found, offset = {}, 8
    while offset < len(data):
        length, kind = struct.unpack_from(">I4s", data, offset)
        found[kind] = data[offset + 8 : offset + 8 + length]
        offset += 12 + length
    return found


def test_real_scans_decode_to_the_pixels_of_a_plain_decode(radiate_sample: Path):
    """Every tiny_foggy scan (1152 px, libpng's Sub/Average/Paeth filters): the square detected over (the whole
    scan, or within 30 m of the radar) and the odometry view equal opencv's own decode of the file."""
    for path in sorted((radiate_sample / "Navtech_Cartesian").glob("*.png")):
        data = path.read_bytes()
        reference = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        for input_size, range_m in ((256, None), (128, 30.0)):
            view = View.of(1152, input_size, RESOLUTION, 4, range_m)
            frame = decode_frame(data, input_size, RESOLUTION, covered=lambda _, side=view.side_px: side)
            side = frame.covered.shape[0]
            assert side == view.side_px == (1152 if range_m is None else 356), path.name
            assert np.array_equal(frame.covered, model_crop(reference, side)), path.name
            assert np.array_equal(frame.odometry_view, model_crop(reference, ODOMETRY_VIEW_SIZE)), path.name


@pytest.mark.parametrize("interlaced", [False, True])
def test_the_decoder_gets_stored_rows_down_to_the_last_row_read(interlaced: bool):
    image = np.random.default_rng(0).integers(0, 256, (64, 64), dtype=np.uint8)
    data = grey_png(image, interlaced=interlaced)
    layout = png.read_layout(png.RawBytes(data))
    file = png.decoder_png(data, layout, rows=40)
    decoded = cv2.imdecode(np.frombuffer(file, np.uint8), cv2.IMREAD_UNCHANGED)
    if interlaced:  # Adam7 rows cannot be cut: the whole image, its IDAT as posted
        assert np.array_equal(decoded, image)
        return
    assert np.array_equal(decoded, image[:40])
    idat = chunks_of(file)[b"IDAT"]
    assert len(idat) > 40 * 65  # stored, not compressed: libpng only copies and unfilters
    assert zlib.decompress(idat) == b"".join(b"\x00" + row.tobytes() for row in image[:40])


def test_a_bad_filter_byte_below_the_rows_read_is_still_refused():
    image = np.zeros((1152, 1152), np.uint8)
    raw = bytearray(b"".join(b"\x00" + row.tobytes() for row in image))
    raw[1100 * 1153] = 9  # row 1100's filter type: none of PNG's five; the service reads rows 0-831 only
    ihdr = struct.pack(">IIBBBBB", 1152, 1152, 8, 0, 0, 0, 0)
    data = b"".join(
        [png.PNG_SIGNATURE, png.png_chunk(b"IHDR", ihdr), png.png_chunk(b"IDAT", zlib.compress(bytes(raw)))]
    )
    data += png.png_chunk(b"IEND", b"")
    with pytest.raises(ApiError, match="row 1100 has an unknown filter type"):
        decode_frame(data, 256, RESOLUTION)


@pytest.mark.parametrize("chunk", [b"IHDR", b"IDAT"])
def test_a_corrupt_crc_of_a_rebuilt_chunk_is_refused(chunk: bytes):
    """The decoder no longer sees the posted IHDR and IDAT chunks, so their CRCs are checked before it."""
    data = bytearray(grey_png(np.full((128, 128), 7, np.uint8)))
    start = data.index(chunk) + 4 + len(chunks_of(bytes(data))[chunk])  # the chunk's CRC
    data[start] ^= 0xFF
    with pytest.raises(ApiError, match="corrupt chunk CRC"):
        decode_frame(bytes(data), 128, RESOLUTION)


@pytest.mark.parametrize("size", [1, 65535, 65536, 3 * 65535 + 7])
def test_stored_blocks_are_a_zlib_stream_of_the_payload(size: int):
    payload = np.random.default_rng(size).integers(0, 256, size, dtype=np.uint8).tobytes()
    stream = b"".join(png.stored_zlib(memoryview(payload)))
    assert zlib.decompress(stream) == payload and len(stream) == size + 2 + 5 * -(-size // 65535) + 4
