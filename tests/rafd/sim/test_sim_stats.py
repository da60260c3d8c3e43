"""Scan statistics, and the simulator's defaults matched to the real tiny_foggy sample."""
from __future__ import annotations

import numpy as np
import pytest

from rafd.geometry import box_to_radiate, radiate_polygon
from rafd.sim import Difficulty, scan_statistics
from rafd.sim.sequence import run_simulation
from rafd.sim.stats import sequence_statistics


def test_scan_statistics_on_a_known_image() -> None:
    image = np.full((64, 64), 10, np.uint8)
    image[10:20, 10:20] = 200
    polygon = np.array([[10.0, 10.0], [20.0, 10.0], [20.0, 20.0], [10.0, 20.0]])
    stats = scan_statistics([image], [[polygon]])
    assert stats.p50 == 10 and stats.p99 == 200
    assert stats.bright_fraction == pytest.approx(100 / 64**2)
    assert stats.contrast > 15
    assert np.isnan(scan_statistics([image], [[]]).contrast)
    with pytest.raises(ValueError):
        scan_statistics([image], [])


def _simulated_stats(size: int, frames: int, seed: int, difficulty: Difficulty = Difficulty()):
    sequence = run_simulation(seed, frames, "test", size, difficulty, name="s")
    polygons = [
        [radiate_polygon(*box_to_radiate(o.boxes[t], size)) for o in sequence.objects if np.isfinite(o.boxes[t, 0])]
        for t in range(frames)
    ]
    return scan_statistics(sequence.images, polygons)


def test_objects_are_brighter_than_background() -> None:
    assert _simulated_stats(512, 4, 2).contrast > 1.5


def test_knobs_move_the_statistics() -> None:
    base = _simulated_stats(384, 2, 4)
    noisy = _simulated_stats(384, 2, 4, Difficulty(noise=4.0))
    assert noisy.p50 > 1.3 * base.p50


def test_defaults_match_the_real_sample(radiate_sample) -> None:
    real = sequence_statistics(radiate_sample)
    sim = _simulated_stats(1152, 6, 0)
    for name in ("p50", "p90", "p99"):
        assert abs(getattr(sim, name) - getattr(real, name)) <= 0.3 * getattr(real, name), (name, sim, real)
    assert real.bright_fraction / 3 < sim.bright_fraction < real.bright_fraction * 3
    assert sim.contrast > 1.5 and real.contrast > 1.5
