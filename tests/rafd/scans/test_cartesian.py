"""rafd.scans.cartesian: a scan PNG's pixels and its size from the header, each failure naming the file; the
Cartesian sides a model accepts."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from rafd.geometry import RADIATE_RESOLUTION, RADIATE_SCAN_SIZE
from rafd.scans.cartesian import accepted_sizes, load_image, png_size


def test_a_scan_png_reads_back_with_its_size_from_the_header(tmp_path: Path):
    scan = np.arange(64 * 48, dtype=np.uint32).reshape(48, 64).astype(np.uint8)
    path = tmp_path / "000001.png"
    cv2.imwrite(str(path), scan)
    assert png_size(path) == (64, 48)
    np.testing.assert_array_equal(load_image(path), scan)


def test_missing_and_broken_files_are_refused_naming_the_file(tmp_path: Path):
    missing = tmp_path / "missing.png"
    for read in (load_image, png_size):
        with pytest.raises(FileNotFoundError, match="missing.png"):
            read(missing)
    broken = tmp_path / "broken.png"
    broken.write_bytes(b"not a png at all, but long enough")
    with pytest.raises(ValueError, match="broken.png.*not a PNG"):
        png_size(broken)
    with pytest.raises(ValueError, match="broken.png.*corrupt"):
        load_image(broken)


def test_a_full_radiate_scan_is_accepted_only_at_radiates_resolution():
    assert accepted_sizes(128, RADIATE_RESOLUTION) == (128, RADIATE_SCAN_SIZE)
    assert accepted_sizes(128, 0.2) == (128,)
    assert accepted_sizes(RADIATE_SCAN_SIZE, RADIATE_RESOLUTION) == (RADIATE_SCAN_SIZE,)
