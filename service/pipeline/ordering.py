"""Arrival order for frames whose stream is named only in their body.

A frame named by the X-Stream-Id header or the path takes its place in its stream at once, by its arrival (the
time its request's first bytes arrived). A frame named only in its body cannot: its stream is known once the body
has arrived and been parsed, and a larger or slower body would lose its place to a later, smaller one. So:

- such a frame is placed once parsed, among the frames of its stream that have not started by its timestamp
  (`StreamStore.place`);
- and a frame does not start its turn while a request of the SAME CLIENT still has its stream unknown (its body
  arriving or being parsed) that was there when the frame became ready, for at most `hold_s` (RAFD_ORDER_HOLD_S).
  Only the same client's requests count: frames of one stream come from one client, and another client's slow
  bodies delay nobody else.

A frame held longer than `hold_s` goes ahead; an earlier frame placed after it started is then refused (409) as
before. All methods run on the event loop.
"""

from __future__ import annotations

import asyncio
import sys
import time
from dataclasses import dataclass, field

from service.pipeline.streams import ArrivalKey

MAX_WAITING_FOR = 64  # unresolved requests tracked per client; more only happen past the per-client request limit


@dataclass(eq=False)
class Unresolved:
    """A request whose stream is not known yet."""

    client: str
    arrival: ArrivalKey
    resolved: asyncio.Event = field(default_factory=asyncio.Event)


class ArrivalOrder:
    def __init__(self, hold_s: float) -> None:
        self.hold_s = hold_s
        self._pending: dict[str, list[Unresolved]] = {}  # per client, in arrival order

    def unresolved(self, client: str) -> int:
        return len(self._pending.get(client, ()))

    def arrive(self, client: str, arrival: ArrivalKey) -> Unresolved:
        """A request of `client` whose stream will be known once its body is parsed."""
        request = Unresolved(client, arrival)
        pending = self._pending.setdefault(client, [])
        pending.append(request)
        pending.sort(key=lambda r: r.arrival)
        return request

    def resolve(self, request: Unresolved) -> None:
        """Its stream is known (and its ticket placed), or it was refused: later frames need not wait for it."""
        pending = self._pending.get(request.client)
        if pending is not None and request in pending:
            pending.remove(request)
            if not pending:
                del self._pending[request.client]
        request.resolved.set()

    async def wait_for_unresolved(self, client: str) -> None:
        """Until the requests of `client` whose stream is unknown NOW are resolved, or `hold_s` passed.

        All of them, not only those stamped before this frame: stamps are taken when the event loop reads a request,
        and a loop busy for a few milliseconds reads the connections that became ready meanwhile in descriptor order,
        so a frame sent just before this one may carry a later stamp. Requests arriving after this call are not
        waited for (a client pipelining without pause cannot hold its own frames back)."""
        if self.hold_s <= 0 or client not in self._pending:
            return
        deadline = time.monotonic() + self.hold_s
        for request in list(self._pending.get(client, ()))[:MAX_WAITING_FOR]:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return
            try:
                await _wait(request.resolved, remaining)
            except asyncio.TimeoutError:
                return


async def _wait(event: asyncio.Event, timeout: float) -> None:
    if sys.version_info >= (3, 11):
        async with asyncio.timeout(timeout):
            await event.wait()
    else:  # Python 3.10
        await asyncio.wait_for(event.wait(), timeout)
