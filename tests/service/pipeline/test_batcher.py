"""service.pipeline.batcher.StepBatcher: ready steps of different streams share a model run while the model is busy (or
within the window when it is idle), each caller gets its own stream's outcome, first frames and unbatchable graphs run
alone, a full queue is refused, a failed batch fails only its own steps and the batcher goes on."""

from __future__ import annotations

import asyncio
import threading
from dataclasses import dataclass

import numpy as np
import pytest

from service.http.errors import ApiError
from service.pipeline.batcher import StepBatcher
from service.pipeline.executors import BoundedExecutor


@dataclass(frozen=True)
class State:
    stream: str
    frames_used: int


class BatchableRunner:
    """step/step_many answer (stream, frame value) so a test sees who got what; `gate` holds the model busy."""

    def __init__(self, batchable: bool = True) -> None:
        self.batchable = batchable
        self.batches: list[list[str]] = []  # streams per model run, in run order
        self.gate = threading.Event()
        self.gate.set()
        self.fail_next = False

    def step(self, state: State, frame: np.ndarray, pose: np.ndarray):
        self.gate.wait(5.0)
        self.batches.append([state.stream])
        return (state.stream, float(frame[0, 0])), State(state.stream, state.frames_used + 1)

    def step_many(self, items):
        self.gate.wait(5.0)
        if self.fail_next:
            self.fail_next = False
            raise RuntimeError("the runtime failed")
        self.batches.append([state.stream for state, _, _ in items])
        return [((s.stream, float(f[0, 0])), State(s.stream, s.frames_used + 1)) for s, f, _ in items]


def frame(value: float) -> np.ndarray:
    return np.full((4, 4), value, np.float32)


def make(runner, workers=1, queue_limit=16, max_batch=4, window_s=0.0) -> StepBatcher:
    return StepBatcher(runner, BoundedExecutor("model", workers, queue_limit, 1), max_batch, window_s)


def test_steps_ready_while_the_model_is_busy_run_as_one_batch_in_arrival_order():
    async def scenario():
        runner = BatchableRunner()
        batcher = make(runner)
        runner.gate.clear()  # the model is busy with stream a's step
        busy = asyncio.create_task(batcher.step(State("a", 1), frame(0.125), np.zeros(3)))
        await asyncio.sleep(0.05)
        waiting = [
            asyncio.create_task(batcher.step(State(name, 2), frame(value), np.zeros(3)))
            for name, value in (("b", 0.25), ("c", 0.5), ("d", 0.75))
        ]
        await asyncio.sleep(0.05)
        assert batcher.waiting == 3
        runner.gate.set()
        results = await asyncio.gather(busy, *waiting)
        return runner, results

    runner, results = asyncio.run(scenario())
    assert runner.batches == [["a"], ["b", "c", "d"]]
    assert [outcome for outcome, _ in results] == [("a", 0.125), ("b", 0.25), ("c", 0.5), ("d", 0.75)]
    assert [state.frames_used for _, state in results] == [2, 3, 3, 3]


def test_the_batch_is_capped_and_the_rest_runs_next():
    async def scenario():
        runner = BatchableRunner()
        batcher = make(runner, max_batch=2)
        runner.gate.clear()
        tasks = [asyncio.create_task(batcher.step(State(s, 1), frame(0.5), np.zeros(3))) for s in "abcde"]
        await asyncio.sleep(0.05)
        runner.gate.set()
        await asyncio.gather(*tasks)
        return runner

    assert asyncio.run(scenario()).batches == [["a"], ["b", "c"], ["d", "e"]]


def test_an_idle_model_waits_the_window_for_company_and_without_a_window_runs_at_once():
    async def scenario(window_s):
        runner = BatchableRunner()
        batcher = make(runner, window_s=window_s)
        first = asyncio.create_task(batcher.step(State("a", 1), frame(0.1), np.zeros(3)))
        await asyncio.sleep(0.01)
        second = asyncio.create_task(batcher.step(State("b", 1), frame(0.2), np.zeros(3)))
        await asyncio.gather(first, second)
        return runner.batches

    assert asyncio.run(scenario(0.2)) == [["a", "b"]]
    assert asyncio.run(scenario(0.0)) == [["a"], ["b"]]


def test_first_frames_and_unbatchable_graphs_run_alone():
    async def scenario(runner, frames_used):
        batcher = make(runner, window_s=0.1)
        await asyncio.gather(*(batcher.step(State(s, frames_used), frame(0.5), np.zeros(3)) for s in "abc"))
        return batcher, runner.batches

    batcher, batches = asyncio.run(scenario(BatchableRunner(), 0))
    assert batches == [["a"], ["b"], ["c"]]
    batcher, batches = asyncio.run(scenario(BatchableRunner(batchable=False), 1))
    assert batcher.max_batch == 1 and batches == [["a"], ["b"], ["c"]]


def test_a_full_queue_is_refused_with_503():
    async def scenario():
        runner = BatchableRunner()
        batcher = make(runner, queue_limit=1)
        runner.gate.clear()
        tasks = [asyncio.create_task(batcher.step(State(s, 1), frame(0.5), np.zeros(3))) for s in "abc"]
        await asyncio.sleep(0.05)
        with pytest.raises(ApiError) as refused:
            await batcher.step(State("d", 1), frame(0.5), np.zeros(3))
        runner.gate.set()
        await asyncio.gather(*tasks)
        return refused.value

    refused = asyncio.run(scenario())
    assert refused.code == "overloaded" and refused.headers == {"Retry-After": "1"}


def test_a_failed_batch_fails_its_steps_only_and_a_cancelled_step_is_dropped():
    async def scenario():
        runner = BatchableRunner()
        batcher = make(runner)
        runner.gate.clear()
        busy = asyncio.create_task(batcher.step(State("a", 0), frame(0.1), np.zeros(3)))  # a first frame: step()
        await asyncio.sleep(0.05)
        doomed = [asyncio.create_task(batcher.step(State(s, 1), frame(0.2), np.zeros(3))) for s in "bc"]
        gone = asyncio.create_task(batcher.step(State("x", 1), frame(0.2), np.zeros(3)))
        await asyncio.sleep(0.05)
        gone.cancel()  # its client went away while it waited
        runner.fail_next = True
        runner.gate.set()
        await busy
        outcomes = await asyncio.gather(*doomed, return_exceptions=True)
        later = await batcher.step(State("d", 1), frame(0.25), np.zeros(3))
        return runner, outcomes, later

    runner, outcomes, later = asyncio.run(scenario())
    assert all(isinstance(o, RuntimeError) for o in outcomes)
    assert later[0] == ("d", 0.25) and runner.batches[-1] == ["d"]
    assert not any("x" in batch for batch in runner.batches)
