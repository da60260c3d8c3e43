"""Cross-stream batching of model steps (Triton's sequence batcher, in small): the steady-state steps of different
streams that are ready at the same time run as one graph run, each stream's caches stacked in and split out
(rafd.runtime.StreamRunner.step_many).

How a step waits: while every model slot (RAFD_CONCURRENT_RUNS) is busy, ready steps gather in the queue and the
next free slot takes up to RAFD_MAX_BATCH of them in arrival order; when the model is idle, the first ready step
waits RAFD_BATCH_WINDOW_MS for company before it runs (0: it runs at once). A stream's frames reach the model one at
a time (the stream store's turn), so a batch never holds two frames of one stream and each stream's order is
unchanged. A stream's first frame (its warm-up runs) and every step of a graph without a batch axis run alone.

Whether it pays is a measurement, per CPU and runtime (docs/performance.md, "Cross-stream batching"): off
(RAFD_MAX_BATCH=1) by default.
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from service.http.errors import ApiError
from service.pipeline.executors import BoundedExecutor


@dataclass
class _Pending:
    state: Any
    frame: np.ndarray
    pose: np.ndarray
    future: asyncio.Future[tuple[Any, Any]] = field(repr=False)
    alone: bool = False  # a stream's first frame: its warm-up runs, never batched


class StepBatcher:
    """`step(state, frame, pose)` -> (result, new state), like runner.step, with ready steps of different streams
    batched on `executor` (the model executor: its workers are the model slots, its queue limit bounds the steps
    waiting here). Event-loop side only."""

    def __init__(self, runner: Any, executor: BoundedExecutor, max_batch: int, window_s: float) -> None:
        self.runner, self.executor = runner, executor
        self.max_batch = max_batch if getattr(runner, "batchable", False) else 1
        self.window_s = window_s
        self.on_batch: Any = None  # called with each run's batch size (metrics)
        self._queue: list[_Pending] = []
        self._running = 0  # batches submitted to the executor and not finished
        self._timer: asyncio.TimerHandle | None = None
        self._tasks: set[asyncio.Task[None]] = set()  # running batches: the loop keeps only weak references

    @property
    def waiting(self) -> int:
        return len(self._queue)

    async def step(self, state: Any, frame: np.ndarray, pose: np.ndarray) -> tuple[Any, Any]:
        if self.max_batch == 1:  # batching off: every step is its own job on the model executor
            if self.on_batch is not None:
                self.on_batch(1)
            return await self.executor.run(self.runner.step, state, frame, pose)
        if len(self._queue) >= self.executor.queue_limit + self.executor.workers:
            raise ApiError(
                "overloaded",
                f"the model queue is full ({len(self._queue)} steps waiting); "
                f"retry after {self.executor.retry_after_s} s",
                headers={"Retry-After": str(self.executor.retry_after_s)},
            )
        pending = _Pending(state, frame, pose, asyncio.get_running_loop().create_future(), state.frames_used == 0)
        self._queue.append(pending)
        self._dispatch()
        return await pending.future

    def _dispatch(self) -> None:
        """Start batches while a model slot is free and steps are ready (waiting out the window when idle)."""
        self._queue = [p for p in self._queue if not p.future.done()]  # requests cancelled while they waited
        while self._queue and self._running < self.executor.workers:
            batch = self._next_batch()
            idle = self._running == 0
            if idle and not batch[0].alone and len(batch) < self.max_batch and self.window_s > 0:
                if self._timer is None:
                    self._timer = asyncio.get_running_loop().call_later(self.window_s, self._window_closed)
                return
            self._start(batch)

    def _next_batch(self) -> list[_Pending]:
        """The queue's head alone if it must run alone, else the batchable steps from the head on (up to the next
        first frame), at most max_batch."""
        if self._queue[0].alone:
            return self._queue[:1]
        batch: list[_Pending] = []
        for pending in self._queue:
            if pending.alone or len(batch) == self.max_batch:
                break
            batch.append(pending)
        return batch

    def _window_closed(self) -> None:
        self._timer = None
        self._queue = [p for p in self._queue if not p.future.done()]
        if self._queue and self._running < self.executor.workers:
            self._start(self._next_batch())
        self._dispatch()

    def _start(self, batch: list[_Pending]) -> None:
        del self._queue[: len(batch)]  # a batch is always the queue's head
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        self._running += 1
        if self.on_batch is not None:
            self.on_batch(len(batch))
        task = asyncio.get_running_loop().create_task(self._run(batch))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _run(self, batch: list[_Pending]) -> None:
        items = [(p.state, p.frame, p.pose) for p in batch]
        try:
            if batch[0].alone:
                outcomes = [await self.executor.run(self.runner.step, *items[0])]
            else:
                outcomes = await self.executor.run(self.runner.step_many, items)
        except asyncio.CancelledError:  # the server is shutting down
            for pending in batch:
                pending.future.cancel()
            raise
        except Exception as error:  # every step of the batch fails the same way (inputs were checked before)
            for pending in batch:
                if not pending.future.done():
                    pending.future.set_exception(error)
        else:
            for pending, outcome in zip(batch, outcomes):
                if not pending.future.done():
                    pending.future.set_result(outcome)
        finally:
            self._running -= 1
            self._dispatch()
