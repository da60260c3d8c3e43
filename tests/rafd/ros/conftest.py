"""Bags written here for the reader and writer tests: native scans in Oxford's layout (tests.rafd.scans.test_native),
recorded as Navtech's driver records them (tools.navtech_bag) or as images."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags", reason="the ROS 2 bag tests need the ros extra")

from tests.rafd.scans.test_native import native_png  # noqa: E402

START_US = 1_547_131_046_000_000


def native_scans(count: int = 3, bins: int = 3768) -> list[np.ndarray]:
    """`count` consecutive native scans (4 Hz) with a return that moves from scan to scan."""
    return [
        native_png(bins, [(30.0 + 5 * k, 20.0), (200.0, 8.0 + k)], 0.0432, start_us=START_US + 250_000 * k, size_m=1.5)
        for k in range(count)
    ]


@pytest.fixture
def scans() -> list[np.ndarray]:
    return native_scans()


@pytest.fixture
def navtech_bag(tmp_path: Path, scans: list[np.ndarray]) -> Path:
    from tools.navtech_bag import write_navtech_bag

    return write_navtech_bag(tmp_path / "navtech", scans, 0.0864)  # a bin size no width would guess
