"""Per-stream state store: one runner StreamState per stream, an arrival-order queue, generations, TTL and LRU.

Arrival order: a frame takes a `Ticket` in its stream's queue when it arrives (before decoding; with the
X-Stream-Id header or the path form even before its body is read), and frames of one stream change the stream
strictly in that order. A frame that can no longer be in order (its timestamp is not after the stream's last
accepted frame, or after that of a frame queued ahead of it) is refused at once instead of waiting its turn.

Exact bookkeeping: only an accepted frame (`commit`) moves a stream in the LRU order or refreshes its idle time;
a refused frame changes nothing, and a new stream whose frames were all refused leaves nothing behind. Each
stream id's chain has a generation: DELETE ends it, and its queued or running frames are refused
(`stream_reset`) instead of continuing the old chain beside the new one.

Expiry is lazy: every store access first drops streams idle past the TTL (never one with frames queued), so no
background task is needed. The LRU cap applies when a request that committed a frame ends; streams with frames
queued are never evicted. All methods run on the event loop (no locking needed).
"""

from __future__ import annotations

import asyncio
import itertools
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from service.errors import ApiError, timestamp_error


@dataclass(eq=False)
class Ticket:
    """One frame's place in its stream's queue."""

    entry: StreamEntry
    timestamp: float | None = None  # None until the body is parsed (header / path form)
    committed: bool = False
    wake: asyncio.Event = field(default_factory=asyncio.Event)


@dataclass(eq=False)
class StreamEntry:
    """One stream chain's buffer and bookkeeping; changed only by the ticket at the head of its queue."""

    stream_id: str
    owner: str | None  # name of the API key that created it (None without API keys)
    generation: int
    state: Any  # the runner's StreamState (holds the last T frames + poses)
    last_used: float  # store clock when its last frame was ACCEPTED
    queue: deque[Ticket] = field(default_factory=deque)  # arrival order; the head is the frame being processed
    closed: bool = False  # deleted: the chain ended, its queued frames are refused
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

    def wake_all(self) -> None:
        for ticket in self.queue:
            ticket.wake.set()

    def out_of_order(self, ticket: Ticket) -> str | None:
        """Why `ticket` can no longer be in order, or None. Only frames AHEAD of it count."""
        t = ticket.timestamp
        if t is None:
            return None
        if self.last_timestamp is not None and t <= self.last_timestamp:
            return f"timestamp {t!r} is not after this stream's last accepted frame ({self.last_timestamp!r})"
        for other in self.queue:
            if other is ticket:
                break
            if other.timestamp is not None and other.timestamp >= t:
                return (
                    f"timestamp {t!r} is not after {other.timestamp!r}, a frame of this stream that arrived "
                    "earlier and is still queued"
                )
        return None


@dataclass(frozen=True)
class StreamInfo:
    stream_id: str
    generation: int
    frames_buffered: int
    frames_seen: int
    frames_queued: int
    last_timestamp: float | None
    idle_s: float
    pose_source: str | None
    state_bytes: int


def _reset_error(entry: StreamEntry) -> ApiError:
    return ApiError(
        "stream_reset",
        f"stream {entry.stream_id!r} (generation {entry.generation}) was deleted while "
        "this frame waited or ran; the frame was not used: send it again to start "
        "the new chain",
    )


class StreamStore:
    """Holds at most `max_streams` streams; evicts idle ones after `ttl_s` and the least recently used at the cap."""

    def __init__(
        self,
        new_state: Callable[[], Any],
        max_streams: int,
        ttl_s: float,
        clock: Callable[[], float] = time.monotonic,
        on_evict: Callable[[str], None] | None = None,
        queue_limit: int = 8,
        retry_after_s: int = 1,
    ) -> None:
        self._new_state = new_state
        self.max_streams = max_streams
        self.ttl_s = ttl_s
        self.queue_limit = queue_limit
        self.retry_after_s = retry_after_s
        self._clock = clock
        self._on_evict = on_evict
        self._entries: OrderedDict[str, StreamEntry] = OrderedDict()  # least recently ACCEPTED first
        self._generations = itertools.count(1)

    def __len__(self) -> int:
        """Streams holding a buffer (at least one accepted frame)."""
        self._expire()
        return sum(1 for e in self._entries.values() if e.frames_seen)

    def __contains__(self, stream_id: str) -> bool:
        return self.get(stream_id) is not None

    def get(self, stream_id: str) -> StreamEntry | None:
        self._expire()
        entry = self._entries.get(stream_id)
        return entry if entry is not None and entry.frames_seen else None

    # ------------------------------------------------------------------ a frame's life
    def take_ticket(self, stream_id: str, owner: str | None = None) -> Ticket:
        """A place at the end of the stream's queue (creating the stream when new); changes nothing else."""
        self._expire()
        entry = self._entries.get(stream_id)
        if entry is None:
            entry = StreamEntry(
                stream_id=stream_id,
                owner=owner,
                generation=next(self._generations),
                state=self._new_state(),
                last_used=self._clock(),
            )
            self._entries[stream_id] = entry
        elif entry.owner != owner:
            raise ApiError("stream_forbidden", f"stream {stream_id!r} belongs to another API key")
        elif len(entry.queue) >= self.queue_limit:
            raise ApiError(
                "stream_queue_full",
                f"{len(entry.queue)} frames of stream {stream_id!r} are already "
                f"queued (RAFD_STREAM_QUEUE_LIMIT); retry after {self.retry_after_s} s",
                headers={"Retry-After": str(self.retry_after_s)},
            )
        ticket = Ticket(entry=entry)
        entry.queue.append(ticket)
        return ticket

    def place(self, ticket: Ticket, timestamp: float) -> None:
        """Give the ticket its timestamp; 409 at once when it can no longer be in order."""
        ticket.timestamp = timestamp
        reason = ticket.entry.out_of_order(ticket)
        if reason:
            raise timestamp_error(ticket.entry.stream_id, reason)
        ticket.entry.wake_all()  # frames behind it with older timestamps can now be refused

    async def wait_turn(self, ticket: Ticket) -> None:
        """Until the ticket heads its stream's queue; refused at once when the chain ends or order is lost."""
        entry = ticket.entry
        while True:
            ticket.wake.clear()
            if entry.closed:
                raise _reset_error(entry)
            reason = entry.out_of_order(ticket)
            if reason:
                raise timestamp_error(entry.stream_id, reason)
            if entry.queue[0] is ticket:
                return
            await ticket.wake.wait()

    def check_turn(self, ticket: Ticket) -> StreamEntry:
        """The entry, once more checked just before the frame changes it (the chain may have ended meanwhile)."""
        if ticket.entry.closed:
            raise _reset_error(ticket.entry)
        return ticket.entry

    def commit(
        self, ticket: Ticket, state: Any, timestamp: float, frame: np.ndarray, pose: np.ndarray, pose_source: str
    ) -> None:
        """The frame was accepted: the only place a stream changes, moves in the LRU order and stops being idle."""
        entry = self.check_turn(ticket)
        assert entry.queue and entry.queue[0] is ticket, "commit out of turn"
        entry.commit(state, timestamp, frame, pose, pose_source)
        entry.last_used = self._clock()
        if self._entries.get(entry.stream_id) is entry:
            self._entries.move_to_end(entry.stream_id)
        ticket.committed = True

    def release(self, ticket: Ticket) -> None:
        """The request ended (answered, refused or failed): leave the queue; apply the cap after a commit."""
        entry = ticket.entry
        try:
            entry.queue.remove(ticket)
        except ValueError:
            return  # released twice
        entry.wake_all()
        if entry.closed or self._entries.get(entry.stream_id) is not entry:
            return
        if entry.frames_seen == 0 and not entry.queue:  # a new stream whose frames were all refused
            del self._entries[entry.stream_id]
        elif ticket.committed:
            self._enforce_cap(keep=entry.stream_id)

    # ------------------------------------------------------------------ resources
    def delete(self, stream_id: str, owner: str | None = None) -> bool:
        """End a stream's chain (its next frame starts a new one); False when unknown. Queued frames get 409."""
        self._expire()
        entry = self._entries.get(stream_id)
        if entry is None or not entry.frames_seen:  # a first frame still in flight is not a stream yet
            return False
        if entry.owner != owner:
            raise ApiError("stream_forbidden", f"stream {stream_id!r} belongs to another API key")
        del self._entries[stream_id]
        entry.closed = True
        entry.wake_all()
        return True

    def snapshot(self, owner: str | None = None) -> list[StreamInfo]:
        """The owner's live streams (all of them without API keys), least recently used first."""
        self._expire()
        now = self._clock()
        return [
            StreamInfo(
                stream_id=e.stream_id,
                generation=e.generation,
                frames_buffered=e.frames_buffered,
                frames_seen=e.frames_seen,
                frames_queued=len(e.queue),
                last_timestamp=e.last_timestamp,
                idle_s=max(0.0, now - e.last_used),
                pose_source=e.pose_source,
                state_bytes=int(getattr(e.state, "nbytes", 0)),
            )
            for e in self._entries.values()
            if e.frames_seen and e.owner == owner
        ]

    # ------------------------------------------------------------------ internals
    def _expire(self) -> None:
        now = self._clock()
        expired = [k for k, e in self._entries.items() if not e.queue and now - e.last_used > self.ttl_s]
        for stream_id in expired:
            del self._entries[stream_id]
            self._evicted("ttl")

    def _enforce_cap(self, keep: str) -> None:
        """Evict least recently used idle streams beyond the cap. Streams with frames queued are skipped (the
        store may then exceed the cap by at most the number of busy streams, until a later frame is accepted).
        `keep`, the stream whose frame was just accepted, is never the one to go."""
        excess = len(self._entries) - self.max_streams
        if excess <= 0:
            return
        for stream_id in [k for k, e in self._entries.items() if not e.queue and k != keep][:excess]:
            del self._entries[stream_id]
            self._evicted("lru")

    def _evicted(self, reason: str) -> None:
        if self._on_evict is not None:
            self._on_evict(reason)
