"""Shared fixtures: the real RADIATE sample is found through RAFD_RADIATE_SAMPLE (set by .ci/run); its real polar
scans through RAFD_RADIATE_POLAR_SAMPLE (default: tiny_foggy_polar beside the sample)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

try:  # the tests' tensors are tiny: a second intra-op thread buys nothing, and where other processes share the
    # cores OpenMP's waiting threads cost seconds per forward (a 64 px model: 2.2 s on 2 threads vs 0.03 s on 1,
    # measured on a loaded 2-core machine). Tests about threads set their own counts.
    import torch

    torch.set_num_threads(1)
except ImportError:  # the serving-only install has no torch
    pass


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


@pytest.fixture(scope="session")
def radiate_polar_sample(radiate_sample: Path) -> Path:
    """Navtech_Polar/ + Navtech_Polar.txt of tiny_foggy's first two frames; skips with the reason when absent."""
    path = Path(os.environ.get("RAFD_RADIATE_POLAR_SAMPLE") or radiate_sample.parent / "tiny_foggy_polar")
    if not (path / "Navtech_Polar").is_dir():
        pytest.skip(
            f"no polar RADIATE sample at {path} (set RAFD_RADIATE_POLAR_SAMPLE to shared/radiate/tiny_foggy_polar)"
        )
    return path


@pytest.fixture(scope="session")
def oxford_sample() -> Path:
    """13 real Oxford Radar RobotCar scans in their native layout with ground-truth odometry (not a test split);
    skips with the reason when RAFD_OXFORD_SAMPLE is not set."""
    path = os.environ.get("RAFD_OXFORD_SAMPLE")
    if not path:
        pytest.skip("RAFD_OXFORD_SAMPLE is not set (point it at shared/oxford_radar_sample; .ci/run does)")
    sample = Path(path)
    if not (sample / "radar").is_dir():
        pytest.skip(f"RAFD_OXFORD_SAMPLE={path} holds no radar/ folder of native scans")
    return sample


@pytest.fixture(scope="session")
def boreas_rt_scan() -> Path:
    """One real Boreas-RT scan (Navtech RAS6, Doppler mode: column 10 is the chirp flag) in the native layout; skips
    with the reason when RAFD_BOREAS_SAMPLE is not set."""
    path = os.environ.get("RAFD_BOREAS_SAMPLE")
    if not path:
        pytest.skip("RAFD_BOREAS_SAMPLE is not set (point it at shared/boreas_rt_sample; .ci/run does)")
    scans = sorted(Path(path).glob("*.png"))
    if not scans:
        pytest.skip(f"RAFD_BOREAS_SAMPLE={path} holds no <microseconds>.png scan")
    return scans[0]


@pytest.fixture(autouse=True)
def _progress_bars_as_a_new_process_has_them():
    """A command run with --quiet silences the process's progress bars (rafd.progress): a test that ran one must
    not silence the next test's."""
    from rafd import progress

    yield
    progress.set_quiet(False)
