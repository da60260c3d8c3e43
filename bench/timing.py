"""Timing calls and summarising latencies (numpy only): one definition for every benchmark and harness."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np


def percentile(values: Sequence[float] | np.ndarray, q: float) -> float:
    """The q-th percentile (0-100, linear interpolation) of `values`; nan when there are none."""
    return float(np.percentile(np.asarray(values, dtype=np.float64), q)) if len(values) else float("nan")


def percentiles(samples_s: Sequence[float]) -> tuple[float, float]:
    """Seconds -> (median ms, p95 ms)."""
    ms = np.asarray(samples_s, dtype=np.float64) * 1000.0
    return percentile(ms, 50), percentile(ms, 95)


def time_calls(call: Callable[[int], Any], repeats: int, warmup: int = 2) -> list[float]:
    """Seconds per call of call(i), after `warmup` untimed calls."""
    for i in range(warmup):
        call(i)
    samples = []
    for i in range(repeats):
        start = time.perf_counter()
        call(i)
        samples.append(time.perf_counter() - start)
    return samples


def time_interleaved(calls: dict[str, Callable[[int], Any]], repeats: int) -> dict[str, list[float]]:
    """Seconds per call of each call(i), one timed call of each per round: load from other jobs hits all alike.

    Each timed call follows one untimed call of the same path: a run leaves its runtime's pool threads busy after
    it returns (onnxruntime's threads spin on the cores for several milliseconds), which would slow whichever path came
    next."""
    samples: dict[str, list[float]] = {name: [] for name in calls}
    for i in range(repeats):
        for name, call in calls.items():
            call(i)  # settles: the previous path's threads are idle again before the timed call
            start = time.perf_counter()
            call(i)
            samples[name].append(time.perf_counter() - start)
    return samples
