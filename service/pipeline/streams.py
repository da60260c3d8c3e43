"""Per-stream state store: one Chain per stream (the model's state and what the service keeps beside it), an
arrival-order queue, generations, TTL and LRU, one namespace per API key.

Namespaces: a stream is (owner, stream id), the owner being the API key's name (None without keys), so A's
`car-7` and B's `car-7` are different streams and no key can tell whether another's id exists. Each owner holds at
most `max_streams_per_key` streams and all owners together `max_streams`; a key over either evicts its OWN least
recently used idle stream, never another key's. Only streams with an accepted frame count: an entry made for
frames still in flight, or whose frames were all refused, counts toward no cap.

Arrival order: a frame holds a `Ticket` in its stream's queue at its place by ARRIVAL (when its request's first
bytes arrived, `service.http.intake`) for its request's life (`queued`: taken on entry, released however the request
ends): from the start with the X-Stream-Id header or the path form, or once its body is parsed when only the body
names the stream (it is then inserted ahead of frames that arrived after it and have not started;
`service.pipeline.ordering` holds those for a bounded time while it is parsed). Once its timestamp is known, a frame
that has not started takes its place among the waiting frames by timestamp (`StreamEntry.order_waiting`: arrival
stamps can invert two requests sent a few milliseconds apart). Frames of one stream change the stream strictly in
queue order. A frame that can no longer be in order (its timestamp is not after the stream's last accepted frame, or
after that of a frame already started) is refused at once instead of waiting its turn, except
the same frame posted again (a retry after a lost answer, same timestamp): it waits its turn and gets the last
frame's answer again when it is that frame (`replay_of`: same image and pose), else it is refused (409).

Exact bookkeeping: only an accepted frame (`commit`) moves a stream in the LRU order or refreshes its idle time;
a refused frame changes nothing, and a new stream whose frames were all refused leaves nothing behind. Each
stream id's chain has a generation: DELETE ends it (also while its first frame is in flight), and its queued or
running frames are refused (`stream_reset`) instead of continuing the old chain beside the new one. A chain ended
by an eviction or the TTL leaves a bounded tombstone, so the next chain's first answer says why it restarted.

Expiry is lazy: every store access first drops streams idle past the TTL (never one with frames queued), so no
background task is needed. The caps apply when a request that committed a frame ends; streams with frames
queued are never evicted. All methods run on the event loop (no locking needed).
"""

from __future__ import annotations

import asyncio
import itertools
import math
import secrets
import time
from collections import Counter, OrderedDict, deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from rafd.runtime import StreamState
from rafd.runtime.view import View
from rafd.tracking import TrackerState
from service.http.errors import ApiError, timestamp_error
from service.schemas import DetectResponse, RestartReason

if TYPE_CHECKING:
    from service.pipeline.poses import OdometryMemory

StreamKey = tuple[str | None, str]  # (owner: the API key's name or None, stream id)
ArrivalKey = tuple[float, int]  # (monotonic time of the request's first bytes, arrival sequence number)
MIN_TOMBSTONES = 64  # per owner; at least 4x its quota (chains ended by eviction or expiry, remembered for a notice)


@dataclass(frozen=True)
class Chain:
    """A stream chain after its last accepted frame: what its next frame continues. Immutable: a frame builds the
    next Chain (`advanced`) and the store swaps it in whole when the frame is accepted (StreamStore.commit)."""

    model: StreamState = field(default_factory=StreamState)  # the runner's state: the model's cache per view
    odometry: OdometryMemory | None = None  # the last frame as the next frame's odometry needs it
    pose: np.ndarray | None = None  # [3] world pose of the last frame
    pose_source: str | None = None  # the chain's FIRST frame's: fixes which world frame the chain uses
    timestamp: float | None = None  # the last frame's
    view: View | None = None  # what its frames are detected over: a frame of another view starts a new chain
    tracks: TrackerState = field(default_factory=TrackerState.empty)  # its boxes' tracks (rafd.tracking)
    token: str = field(default_factory=lambda: secrets.token_hex(4))  # its track ids' prefix: new with every chain

    def advanced(
        self,
        model: StreamState,
        odometry: OdometryMemory,
        pose: np.ndarray,
        pose_source: str,
        timestamp: float,
        view: View,
        tracks: TrackerState,
    ) -> Chain:
        """The chain once one more frame is accepted."""
        return Chain(model, odometry, pose, self.pose_source or pose_source, timestamp, view, tracks, self.token)

    @property
    def nbytes(self) -> int:
        """What the chain's model state and tracks hold (the odometry's memory is counted apart)."""
        return self.model.nbytes + self.tracks.nbytes


@dataclass(eq=False)
class Ticket:
    """One frame's place in its stream's queue."""

    entry: StreamEntry
    arrival: ArrivalKey
    timestamp: float | None = None  # None until the body is parsed (header / path form)
    started: bool = False  # its turn came: it heads the queue and may change the stream
    committed: bool = False
    restarted: RestartReason | None = None  # set when it committed the first frame of a chain restarted by the store
    wake: asyncio.Event = field(default_factory=asyncio.Event)


@dataclass(eq=False)
class StreamEntry:
    """One stream chain's buffer and bookkeeping; changed only by the ticket at the head of its queue."""

    stream_id: str
    owner: str | None  # name of the API key whose namespace holds it (None without API keys)
    generation: int
    last_used: float  # store clock when its last frame was ACCEPTED
    chain: Chain = field(default_factory=Chain)
    queue: deque[Ticket] = field(default_factory=deque)  # arrival order; the head is the frame being processed
    closed: bool = False  # deleted: the chain ended, its queued frames are refused
    frames_seen: int = 0
    restarted: RestartReason | None = None  # how the previous chain of this id ended, when the store ended it
    # The last accepted frame's identity (digest of its image and pose) and its answer: the same frame posted again
    # (a retry after a lost answer) is answered with that answer, not refused and not stepped twice.
    last_digest: bytes | None = None
    last_answer: DetectResponse | None = None

    @property
    def key(self) -> StreamKey:
        return (self.owner, self.stream_id)

    @property
    def last_timestamp(self) -> float | None:
        return self.chain.timestamp

    @property
    def frames_buffered(self) -> int:
        return self.chain.model.frames_used

    def commit(self, chain: Chain, digest: bytes | None = None) -> None:
        """Swap in the chain a frame advanced (only after it succeeded whole) and the frame's bookkeeping."""
        self.chain = chain
        self.frames_seen += 1
        self.last_digest = digest
        self.last_answer = None  # set once the answer is complete (`remember_answer`)

    def remember_answer(self, timestamp: float, digest: bytes | None, answer: DetectResponse) -> None:
        """Keep the answer of the frame just accepted (when it is still the last one) for a retry of it."""
        if digest is not None and timestamp == self.last_timestamp and digest == self.last_digest:
            self.last_answer = answer

    def replay_of(self, timestamp: float, digest: bytes | None) -> DetectResponse | None:
        """The last accepted frame's answer when this frame is that frame again (same timestamp and digest)."""
        if digest is None or self.last_answer is None or timestamp != self.last_timestamp:
            return None
        return self.last_answer if digest == self.last_digest else None

    def wake_all(self) -> None:
        for ticket in self.queue:
            ticket.wake.set()

    def out_of_order(self, ticket: Ticket) -> str | None:
        """Why `ticket` can no longer be in order, or None. Only frames AHEAD of it count."""
        t = ticket.timestamp
        if t is None:
            return None
        if self.last_timestamp is not None and t <= self.last_timestamp:
            # Equal: maybe the last frame again (a retry), answered again at its turn if it is (`replay_of`).
            if not (t == self.last_timestamp and self.last_answer is not None):
                return f"timestamp {t!r} is not after this stream's last accepted frame ({self.last_timestamp!r})"
        for other in self.queue:
            if other is ticket:
                break
            # Equal: a retry of a frame still queued or running waits for it (then replays it, or takes its place).
            # Only a started frame can be ahead with a later timestamp: the waiting ones are in timestamp order.
            if other.timestamp is not None and other.timestamp > t:
                return (
                    f"timestamp {t!r} is not after {other.timestamp!r}, a frame of this stream that arrived "
                    "earlier and is still queued"
                )
        return None

    def order_waiting(self) -> None:
        """Put the frames that have not started and whose timestamps are known in timestamp order (by arrival among
        equal ones), each into one of their slots; a frame whose body is still arriving keeps its place by arrival.

        Arrival order alone is not the client's order: requests of one client on separate connections are stamped
        when the event loop reads them, and a loop busy for a few milliseconds reads the sockets that became ready
        meanwhile in descriptor order. Frames that have not started can still be taken in the order the stream
        needs, so one sent a little later but read first does not get its predecessor refused."""
        slots = [k for k, t in enumerate(self.queue) if not t.started and t.timestamp is not None]
        waiting = sorted((self.queue[k] for k in slots), key=lambda t: (t.timestamp, t.arrival))
        for k, ticket in zip(slots, waiting):
            self.queue[k] = ticket


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
    """Holds at most `max_streams` streams (`max_streams_per_key` per owner); evicts idle ones after `ttl_s` and, at a
    cap, the owner's own least recently used."""

    def __init__(
        self,
        max_streams: int,
        ttl_s: float,
        clock: Callable[[], float] = time.monotonic,
        on_evict: Callable[[str], None] | None = None,
        queue_limit: int = 8,
        retry_after_s: int = 1,
        max_streams_per_key: int | None = None,
        on_restart: Callable[[str], None] | None = None,
    ) -> None:
        self.max_streams = max_streams
        self.max_streams_per_key = min(max_streams_per_key or max_streams, max_streams)
        self.ttl_s = ttl_s
        self.queue_limit = queue_limit
        self.retry_after_s = retry_after_s
        self._clock = clock
        self._on_evict = on_evict
        self._on_restart = on_restart
        self._entries: OrderedDict[StreamKey, StreamEntry] = OrderedDict()  # least recently ACCEPTED first
        self._accepted: Counter[str | None] = Counter()  # streams with an accepted frame, per owner
        self._tombstones: dict[str | None, OrderedDict[str, RestartReason]] = {}
        self._generations = itertools.count(1)
        self._arrivals = itertools.count()  # order of tickets taken without an arrival (direct use, tests)

    def __len__(self) -> int:
        """Streams holding a buffer (at least one accepted frame)."""
        self._expire()
        return sum(self._accepted.values())

    def __contains__(self, stream_id: str) -> bool:
        return self.get(stream_id) is not None

    def get(self, stream_id: str, owner: str | None = None) -> StreamEntry | None:
        self._expire()
        entry = self._entries.get((owner, stream_id))
        return entry if entry is not None and entry.frames_seen else None

    # ------------------------------------------------------------------ a frame's life
    @contextmanager
    def queued(self, stream_id: str, owner: str | None = None, arrival: ArrivalKey | None = None) -> Iterator[Ticket]:
        """The frame's place in its stream's queue (`take_ticket`) for the request's life, left (`release`) however
        the request ends."""
        ticket = self.take_ticket(stream_id, owner, arrival)
        try:
            yield ticket
        finally:
            self.release(ticket)

    def take_ticket(self, stream_id: str, owner: str | None = None, arrival: ArrivalKey | None = None) -> Ticket:
        """A place in the stream's queue by arrival (creating the stream's entry when new); changes nothing else.

        Placed after every frame that arrived before it and ahead of those that arrived after it and have not
        started (a frame whose stream was only known once its body was parsed); never ahead of a started frame."""
        self._expire()
        key = (owner, stream_id)
        entry = self._entries.get(key)
        if entry is None:
            entry = StreamEntry(
                stream_id=stream_id,
                owner=owner,
                generation=next(self._generations),
                last_used=self._clock(),
                restarted=self._tombstone(owner, stream_id),
            )
            self._entries[key] = entry
        elif len(entry.queue) >= self.queue_limit:
            raise ApiError(
                "stream_queue_full",
                f"{len(entry.queue)} frames of stream {stream_id!r} are already "
                f"queued (RAFD_STREAM_QUEUE_LIMIT); retry after {self.retry_after_s} s",
                headers={"Retry-After": str(self.retry_after_s)},
            )
        ticket = Ticket(entry=entry, arrival=arrival if arrival is not None else (math.inf, next(self._arrivals)))
        queue = entry.queue
        position = len(queue)
        while position > 0 and not queue[position - 1].started and queue[position - 1].arrival > ticket.arrival:
            position -= 1
        queue.insert(position, ticket)
        if position < len(queue) - 1:
            entry.wake_all()  # the frames behind it check their order against it once it is placed
        return ticket

    def place(self, ticket: Ticket, timestamp: float) -> None:
        """Give the ticket its timestamp and its place among the waiting frames (StreamEntry.order_waiting); 409 at
        once when it can no longer be in order."""
        ticket.timestamp = timestamp
        ticket.entry.order_waiting()
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
                ticket.started = True  # no frame is placed ahead of it from now on
                return
            await ticket.wake.wait()

    def check_turn(self, ticket: Ticket) -> StreamEntry:
        """The entry, once more checked just before the frame changes it (the chain may have ended meanwhile)."""
        if ticket.entry.closed:
            raise _reset_error(ticket.entry)
        return ticket.entry

    def commit(
        self, ticket: Ticket, chain: Chain, digest: bytes | None = None, chain_break: RestartReason | None = None
    ) -> None:
        """The frame was accepted with the chain it advanced: the only place a stream changes, moves in the LRU order
        and stops being idle.

        `chain_break`: the frame found the chain held here stale or not its own and was stepped on a fresh chain; the
        entry starts a new chain (a new generation) with it, and its answer says why."""
        entry = self.check_turn(ticket)
        assert entry.queue and entry.queue[0] is ticket, "commit out of turn"
        new_chain = chain_break is not None and entry.frames_seen > 0
        entry.commit(chain, digest)
        if new_chain:
            entry.generation = next(self._generations)
            ticket.restarted = chain_break
            if self._on_restart is not None and chain_break is not None:
                self._on_restart(chain_break)
        entry.last_used = self._clock()
        if self._entries.get(entry.key) is entry:
            self._entries.move_to_end(entry.key)
        if entry.frames_seen == 1:  # the chain's first accepted frame: the stream now counts toward the caps
            self._accepted[entry.owner] += 1
            if entry.restarted is not None:
                ticket.restarted = entry.restarted
                self._forget_tombstone(entry.owner, entry.stream_id)
                if self._on_restart is not None:
                    self._on_restart(entry.restarted)
        ticket.committed = True

    def release(self, ticket: Ticket) -> None:
        """The request ended (answered, refused or failed): leave the queue; apply the caps after a commit."""
        entry = ticket.entry
        try:
            entry.queue.remove(ticket)
        except ValueError:
            return  # released twice
        entry.wake_all()
        if entry.closed or self._entries.get(entry.key) is not entry:
            return
        if entry.frames_seen == 0 and not entry.queue:  # a new stream whose frames were all refused
            del self._entries[entry.key]
        elif ticket.committed:
            self._enforce_caps(entry)

    # ------------------------------------------------------------------ resources
    def delete(self, stream_id: str, owner: str | None = None) -> bool:
        """End the owner's stream chain (its next frame starts a new one), also while its first frame is in flight
        (that frame gets 409 `stream_reset`, as queued frames do); False when it has neither an accepted frame nor
        a frame in flight."""
        self._expire()
        entry = self._entries.get((owner, stream_id))
        if entry is None or not (entry.frames_seen or entry.queue):
            return False
        self._remove(entry)
        entry.closed = True
        entry.wake_all()
        self._forget_tombstone(owner, stream_id)  # a reset the client asked for: no notice
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
                pose_source=e.chain.pose_source,
                state_bytes=e.chain.nbytes,
            )
            for e in self._entries.values()
            if e.frames_seen and e.owner == owner
        ]

    # ------------------------------------------------------------------ internals
    def _remove(self, entry: StreamEntry) -> None:
        del self._entries[entry.key]
        if entry.frames_seen:
            self._accepted[entry.owner] -= 1
            if not self._accepted[entry.owner]:
                del self._accepted[entry.owner]

    def _tombstone(self, owner: str | None, stream_id: str) -> RestartReason | None:
        tombstones = self._tombstones.get(owner)
        return tombstones.get(stream_id) if tombstones is not None else None

    def _forget_tombstone(self, owner: str | None, stream_id: str) -> None:
        tombstones = self._tombstones.get(owner)
        if tombstones is not None:
            tombstones.pop(stream_id, None)

    def _end(self, entry: StreamEntry, reason: RestartReason) -> None:
        """The store ended an idle chain: forget it, and remember why for its id's next answer."""
        self._remove(entry)
        tombstones = self._tombstones.setdefault(entry.owner, OrderedDict())
        tombstones.pop(entry.stream_id, None)
        tombstones[entry.stream_id] = reason
        while len(tombstones) > max(MIN_TOMBSTONES, 4 * self.max_streams_per_key):
            tombstones.popitem(last=False)
        if self._on_evict is not None:
            self._on_evict("ttl" if reason == "expired" else "lru")

    def _expire(self) -> None:
        now = self._clock()
        expired = [e for e in self._entries.values() if not e.queue and now - e.last_used > self.ttl_s]
        for entry in expired:
            self._end(entry, "expired")

    def _enforce_caps(self, entry: StreamEntry) -> None:
        """Evict the owner's least recently used idle streams beyond its quota or the store's cap; never another
        owner's. Streams with frames queued are skipped (the store may then exceed a cap by at most the number of
        busy streams, until a later frame is accepted). `entry`, whose frame was just accepted, is never the one to
        go."""
        owner = entry.owner
        excess = max(self._accepted[owner] - self.max_streams_per_key, sum(self._accepted.values()) - self.max_streams)
        if excess <= 0:
            return
        victims = [
            e for e in self._entries.values() if e.owner == owner and e.frames_seen and not e.queue and e is not entry
        ]
        for victim in victims[:excess]:
            self._end(victim, "evicted")
