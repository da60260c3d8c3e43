"""Hand-made PNG files for the service tests: any bit depth / colour type, interlaced, padded, bombs."""

from __future__ import annotations

import struct
import zlib

import numpy as np

from service.body.png import ADAM7, PNG_SIGNATURE
from service.body.png import png_chunk as chunk


def ihdr(width: int, height: int, depth: int = 8, colour: int = 0, interlace: int = 0) -> bytes:
    return chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, interlace))


def scanlines(image: np.ndarray, interlaced: bool = False) -> bytes:
    """uint8 [H, W] grey -> filtered scanlines (filter type 0 on every row), Adam7 passes when interlaced."""
    passes = ADAM7 if interlaced else ((0, 0, 1, 1),)
    out = []
    for row0, col0, row_step, col_step in passes:
        sub = image[row0::row_step, col0::col_step]
        if sub.size:
            out += [b"\x00" + row.tobytes() for row in sub]
    return b"".join(out)


def grey_png(
    image: np.ndarray,
    interlaced: bool = False,
    before_idat: bytes = b"",
    after_idat: bytes = b"",
    extra_compressed: int = 0,
    idat_size: int = 8192,
    trailing: bytes = b"",
    declared: tuple[int, int] | None = None,
) -> bytes:
    """An 8-bit greyscale PNG; `before_idat` / `after_idat`: raw chunks inserted; `extra_compressed`: that many
    zero bytes deflated into the image stream after the last row (libpng inflates them all); `declared`:
    (width, height) written in IHDR instead of the image's."""
    height, width = image.shape[0], image.shape[1]
    if declared is not None:
        width, height = declared
    compressor = zlib.compressobj(6)
    stream = compressor.compress(scanlines(image, interlaced))
    if extra_compressed:
        stream += compressor.compress(bytes(extra_compressed))
    stream += compressor.flush()
    idat = b"".join(chunk(b"IDAT", stream[i : i + idat_size]) for i in range(0, len(stream), idat_size))
    return (
        PNG_SIGNATURE
        + ihdr(width, height, interlace=int(interlaced))
        + before_idat
        + idat
        + after_idat
        + chunk(b"IEND", b"")
        + trailing
    )


def text_chunks(count: int, size: int = 8000, compressed: bool = True) -> bytes:
    """`count` zTXt (or tEXt) chunks, each inflating to `size` bytes of text: the padded-PNG flood's payload."""
    if compressed:
        body = b"comment\x00\x00" + zlib.compress(b"A" * size, 9)
        return chunk(b"zTXt", body) * count
    return chunk(b"tEXt", b"comment\x00" + b"A" * size) * count


def padded_scan(scan_png: bytes, target_bytes: int = 7_700_000, inflated_per_chunk: int = 8_000_000) -> bytes:
    """A valid PNG padded with zTXt chunks right after IHDR up to about `target_bytes` (issue 14, finding 1)."""
    one = text_chunks(1, inflated_per_chunk)
    count = max(1, (target_bytes - len(scan_png)) // len(one))
    return scan_png[:33] + one * count + scan_png[33:]


def other_format_png(width: int, height: int, depth: int, colour: int) -> bytes:
    """A valid-looking PNG of another format (1-bit grey, palette, RGB...): all-zero pixels."""
    channels = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}[colour]
    row_bytes = -(-width * channels * depth // 8)
    raw = (b"\x00" + bytes(row_bytes)) * height
    plte = chunk(b"PLTE", bytes(3 * 2)) if colour == 3 else b""
    return (
        PNG_SIGNATURE
        + ihdr(width, height, depth, colour)
        + plte
        + chunk(b"IDAT", zlib.compress(raw))
        + chunk(b"IEND", b"")
    )
