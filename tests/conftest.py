"""Shared fixtures: the real RADIATE sample is found through RAFD_RADIATE_SAMPLE (set by .ci/run)."""
from __future__ import annotations

import os
from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def radiate_sample() -> Path:
    """The real 18-frame tiny_foggy sequence; skips with the reason when it is not available."""
    path = os.environ.get("RAFD_RADIATE_SAMPLE")
    if not path:
        pytest.skip("RAFD_RADIATE_SAMPLE is not set (point it at shared/radiate/tiny_foggy; .ci/run does)")
    sample = Path(path)
    if not (sample / "Navtech_Cartesian").is_dir():
        pytest.skip(f"RAFD_RADIATE_SAMPLE={path} holds no Navtech_Cartesian/ folder")
    return sample
