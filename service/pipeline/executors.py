"""Bounded executors: JSON parsing, decoding, odometry and the model each get their own threads and queue limit.

Why: with one shared thread pool, 45 slow decodes in flight made /health/ready take 19 s and a normal /detect up to
67 s. Here a job waits only behind jobs of its own kind, a full queue answers 503 `overloaded` with Retry-After
at once (the work is refused before it is spent), and the event loop, which answers health and metrics, never
waits on any of them.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, TypeVar

from service.http.errors import ApiError

T = TypeVar("T")


class BoundedExecutor:
    """`workers` threads; at most `queue_limit` jobs wait for one. Beyond that, submit answers 503 at once."""

    def __init__(
        self,
        name: str,
        workers: int,
        queue_limit: int,
        retry_after_s: int,
        on_refused: Callable[[str], None] | None = None,
    ) -> None:
        self.name = name
        self.workers = workers
        self.queue_limit = queue_limit
        self.retry_after_s = retry_after_s
        self._pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix=f"rafd-{name}")
        self._lock = threading.Lock()
        self._pending = 0  # submitted and not finished (running + waiting); decremented by the worker thread
        self._on_refused = on_refused

    @property
    def pending(self) -> int:
        with self._lock:
            return self._pending

    @property
    def waiting(self) -> int:
        """Jobs queued behind the running ones."""
        return max(0, self.pending - self.workers)

    def _finished(self, _: Future[Any]) -> None:
        with self._lock:
            self._pending -= 1

    async def run(self, fn: Callable[..., T], *args: object) -> T:
        """fn(*args) on this executor's threads; ApiError 503 when its queue is full."""
        with self._lock:
            full = self._pending >= self.workers + self.queue_limit
            if not full:
                self._pending += 1
        if full:
            if self._on_refused is not None:
                self._on_refused(self.name)
            raise ApiError(
                "overloaded",
                f"the {self.name} queue is full ({self.queue_limit} jobs waiting for "
                f"{self.workers} worker(s)); retry after {self.retry_after_s} s",
                headers={"Retry-After": str(self.retry_after_s)},
            )
        future = self._pool.submit(fn, *args)
        # Counted down when the job really ends, even if the awaiting request was cancelled meanwhile.
        future.add_done_callback(self._finished)
        return await asyncio.wrap_future(future)

    def shutdown(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)


class AdmissionLimit:
    """At most `limit` /detect requests at once in one stage: receiving their body (RAFD_MAX_RECEIVING_REQUESTS), or
    with their body arrived (RAFD_MAX_INFLIGHT_REQUESTS; each holds a body of up to RAFD_MAX_REQUEST_BYTES)."""

    def __init__(self, limit: int, retry_after_s: int, what: str = "in flight", setting: str = "MAX_INFLIGHT_REQUESTS"):
        self.limit = limit
        self.retry_after_s = retry_after_s
        self.what = what
        self.setting = setting
        self.in_flight = 0  # event loop only

    def enter(self) -> None:
        if self.in_flight >= self.limit:
            raise ApiError(
                "overloaded",
                f"{self.limit} detect requests are already {self.what} "
                f"(RAFD_{self.setting}); retry after {self.retry_after_s} s",
                headers={"Retry-After": str(self.retry_after_s)},
            )
        self.in_flight += 1

    def leave(self) -> None:
        self.in_flight -= 1
