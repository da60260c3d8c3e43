"""Interleaved timing: one path's leftover work is not charged to the next; percentiles."""

from __future__ import annotations

import math
import time

from bench.timing import percentile, percentiles, time_interleaved


def test_interleaved_timing_is_not_charged_for_the_path_before():
    """A run can leave work behind it (onnxruntime's pool threads spin on the cores after a run returns): the path
    timed next must not pay for it. Here every call pays 20 ms when another path ran just before it, 0 otherwise."""
    last = {"name": None}

    def path(name: str):
        def call(_: int) -> None:
            if last["name"] not in (None, name):
                time.sleep(0.02)  # the previous path's leftover work
            last["name"] = name

        return call

    samples = time_interleaved({"a": path("a"), "b": path("b")}, repeats=3)
    assert set(samples) == {"a", "b"} and all(len(s) == 3 for s in samples.values())
    assert max(max(s) for s in samples.values()) < 0.01


def test_percentiles_are_in_milliseconds_and_empty_is_nan():
    assert percentiles([0.001, 0.002, 0.003]) == (2.0, 2.9)
    assert percentile([5.0, 1.0, 3.0], 50) == 3.0 and math.isnan(percentile([], 99))
