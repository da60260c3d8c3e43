"""Per-stream state store: one runner StreamState per stream, a per-stream lock, idle TTL and an LRU cap.

All methods are called from the event loop; the thread lock only guards against use from worker threads.
The LRU cap is applied when a request ends (after its frame was committed), so a refused request can
never evict another stream.
Expiry is lazy: every store access first drops streams idle for longer than the TTL, so no background
task is needed and `GET /streams` / the metrics never show an expired stream.
"""
from __future__ import annotations

import asyncio
import threading
import time
from collections import OrderedDict
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np



@dataclass
class StreamEntry:
    """One stream's buffer and bookkeeping; changed only while its `lock` is held."""

    stream_id: str
    state: Any  # the runner's StreamState (holds the last T frames + poses)
    last_used: float  # store clock at the end of the last request
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)
    busy: int = 0  # requests holding or waiting for the lock: such a stream is never evicted
    frames_seen: int = 0
    last_timestamp: float | None = None
    last_frame: np.ndarray | None = None  # [V, V] uint8 odometry view of the last accepted frame
    last_pose: np.ndarray | None = None  # [3] world pose of the last accepted frame
    pose_source: str | None = None  # source of the FIRST frame: fixes which world frame the stream uses

    @property
    def frames_buffered(self) -> int:
        return int(self.state.frames_used)

    def commit(self, state: Any, timestamp: float, frame: np.ndarray, pose: np.ndarray, pose_source: str) -> None:
        """Swap in the runner's new state and the frame's bookkeeping (only after a successful step)."""
        self.state = state
        self.last_timestamp = timestamp
        self.last_frame = frame
        self.last_pose = pose
        if self.pose_source is None:
            self.pose_source = pose_source
        self.frames_seen += 1


@dataclass(frozen=True)
class StreamInfo:
    stream_id: str
    frames_buffered: int
    frames_seen: int
    last_timestamp: float | None
    idle_s: float
    pose_source: str | None
    state_bytes: int


class StreamStore:
    """Holds at most `max_streams` streams; evicts idle ones after `ttl_s` and the least recently used at the cap."""

    def __init__(
        self,
        new_state: Callable[[], Any],
        max_streams: int,
        ttl_s: float,
        clock: Callable[[], float] = time.monotonic,
        on_evict: Callable[[str], None] | None = None,
    ) -> None:
        self._new_state = new_state
        self.max_streams = max_streams
        self.ttl_s = ttl_s
        self._clock = clock
        self._on_evict = on_evict
        self._entries: OrderedDict[str, StreamEntry] = OrderedDict()  # least recently used first
        self._mutex = threading.Lock()

    def __len__(self) -> int:
        with self._mutex:
            self._expire()
            return len(self._entries)

    def __contains__(self, stream_id: str) -> bool:
        with self._mutex:
            self._expire()
            return stream_id in self._entries

    @asynccontextmanager
    async def session(self, stream_id: str) -> AsyncIterator[StreamEntry]:
        """Hold `stream_id`'s lock (creating the stream when new): requests of one stream run one at a time."""
        entry = self._checkout(stream_id)
        try:
            async with entry.lock:
                yield entry
        finally:
            with self._mutex:
                entry.busy -= 1
                entry.last_used = self._clock()
                if self._entries.get(stream_id) is entry:
                    self._entries.move_to_end(stream_id)
                    # A new stream whose first frame was refused leaves nothing behind (and evicted nothing).
                    if entry.frames_seen == 0 and entry.busy == 0:
                        del self._entries[stream_id]
                    self._enforce_cap(keep=stream_id)

    def delete(self, stream_id: str) -> bool:
        """Forget a stream (its next frame starts a new buffer); False when unknown."""
        with self._mutex:
            self._expire()
            return self._entries.pop(stream_id, None) is not None

    def snapshot(self) -> list[StreamInfo]:
        """Every live stream, least recently used first."""
        with self._mutex:
            self._expire()
            now = self._clock()
            return [
                StreamInfo(
                    stream_id=e.stream_id,
                    frames_buffered=e.frames_buffered,
                    frames_seen=e.frames_seen,
                    last_timestamp=e.last_timestamp,
                    idle_s=0.0 if e.busy else max(0.0, now - e.last_used),
                    pose_source=e.pose_source,
                    state_bytes=int(getattr(e.state, "nbytes", 0)),
                )
                for e in self._entries.values()
                if e.frames_seen > 0
            ]

    def get(self, stream_id: str) -> StreamEntry | None:
        with self._mutex:
            self._expire()
            return self._entries.get(stream_id)

    # ------------------------------------------------------------------ internals (mutex held)
    def _checkout(self, stream_id: str) -> StreamEntry:
        with self._mutex:
            self._expire()
            entry = self._entries.get(stream_id)
            if entry is None:
                entry = StreamEntry(stream_id=stream_id, state=self._new_state(), last_used=self._clock())
                self._entries[stream_id] = entry
            self._entries.move_to_end(stream_id)
            entry.busy += 1
            return entry

    def _expire(self) -> None:
        now = self._clock()
        expired = [k for k, e in self._entries.items() if not e.busy and now - e.last_used > self.ttl_s]
        for stream_id in expired:
            del self._entries[stream_id]
            self._evicted("ttl")

    def _enforce_cap(self, keep: str) -> None:
        """Evict least recently used idle streams beyond the cap. Runs when a request ends, so a refused
        first frame never evicts anyone; streams with requests in flight are skipped (the store may then
        exceed the cap by at most the number of concurrent requests, until they finish). `keep`, the stream
        whose request just ended, is the most recently used and never the one to go."""
        excess = len(self._entries) - self.max_streams
        for stream_id in [k for k, e in self._entries.items() if not e.busy and k != keep][: max(0, excess)]:
            del self._entries[stream_id]
            self._evicted("lru")

    def _evicted(self, reason: str) -> None:
        if self._on_evict is not None:
            self._on_evict(reason)
