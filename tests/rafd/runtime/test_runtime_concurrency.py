"""Concurrent runs: a run alone takes the all-threads backend, overlapping runs the shared-out one, never more than
concurrent_runs at once; results do not depend on which backend ran them."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from rafd.config import RaFDConfig
from rafd.runtime import OnnxRunner, StreamRunner


class RecordingBackend:
    """A stand-in graph with the step contract (T = 2) that records who ran and how many ran at once."""

    runtime, precision = "fake", "fp32"

    def __init__(self, name: str, threads: int, concurrent_runs: int, log: list, counter: dict) -> None:
        cfg = RaFDConfig.tiny(input_size=16, num_frames=2)
        self.name, self.threads, self.concurrent_runs, self.log, self.counter = (
            name,
            threads,
            concurrent_runs,
            log,
            counter,
        )
        self.metadata = {"config": cfg.to_json()}
        self.input_shapes = {"frame": (1, 1, 16, 16), "pose": (1, 3), "cache.state": (1, 4)}
        self.output_names = ("heatmap", "scores", "boxes", "flow", "frames_used", "new_cache.state")

    def run(self, feeds):
        with self.counter["lock"]:
            self.counter["now"] += 1
            self.counter["max"] = max(self.counter["max"], self.counter["now"])
        time.sleep(0.03)
        with self.counter["lock"]:
            self.counter["now"] -= 1
        self.log.append(self.name)
        return {}


ONE = {"frame": np.zeros((1, 1, 16, 16), np.float32)}  # a batch of one


@pytest.fixture
def runner_and_log():
    log, counter = [], {"lock": threading.Lock(), "now": 0, "max": 0}
    runner = StreamRunner(RecordingBackend("alone", 2, 1, log, counter), RecordingBackend("crowd", 1, 2, log, counter))
    return runner, log, counter


def test_a_lone_run_uses_all_threads(runner_and_log):
    runner, log, _ = runner_and_log
    for _ in range(3):
        runner.run(ONE)
    assert log == ["alone"] * 3
    assert runner.describe()["threads"] == 2 and runner.describe()["threads_per_concurrent_run"] == 1


def test_overlapping_runs_share_the_cores_and_are_capped(runner_and_log):
    runner, log, counter = runner_and_log
    threads = [threading.Thread(target=runner.run, args=(ONE,)) for _ in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert len(log) == 8 and counter["max"] == 2  # concurrent_runs = 2: never more at once
    assert "crowd" in log  # runs that started beside another one used the shared-out backend


def test_a_crowd_backend_must_run_the_same_graph(runner_and_log):
    runner, log, counter = runner_and_log
    other = RecordingBackend("crowd", 1, 2, log, counter)
    other.precision = "bf16"
    with pytest.raises(ValueError, match="same graph"):
        StreamRunner(runner.backend, other)


def test_real_runner_gives_the_same_results_alone_and_in_a_crowd(shipped_onnx):
    runner = OnnxRunner(shipped_onnx, threads=2, concurrent_runs=2)
    assert runner.crowd is not None and runner.crowd.threads == 1 and runner.backend.threads == 2
    cfg = runner.config
    rng = np.random.default_rng(0)
    frames = (rng.random((4, cfg.input_size, cfg.input_size)) * 0.4).astype(np.float32)
    poses = np.cumsum(np.tile([[0.1, 1.5, 0.02]], (4, 1)), axis=0)

    def stream():
        state, out = runner.new_state(), []
        for frame, pose in zip(frames, poses):
            result, state = runner.step(state, frame[None], pose[None])
            out.append(result)
        return out

    alone = stream()
    results = [None] * 4
    workers = [threading.Thread(target=lambda i=i: results.__setitem__(i, stream())) for i in range(4)]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join()
    for crowd in results:
        for a, b in zip(alone, crowd):
            np.testing.assert_allclose(b.heatmap, a.heatmap, atol=1e-4, rtol=1e-4)
            np.testing.assert_allclose(b.flow, a.flow, atol=1e-4, rtol=1e-4)
