"""What a client may send before it is authenticated, at the ASGI level (the HTTP server limits the request head
itself: service/http/head_limits.py):

- every request gets its ARRIVAL: when its first bytes arrived (stamped by the server's protocol, else on entry
  here) and an arrival number, the order frames of a stream are served in (service/pipeline/streams.py);
- a client (by address: behind a trusted proxy, its X-Forwarded-For as uvicorn resolves it) has at most
  `max_per_client` unfinished requests on every route but the health probes; beyond, 429
  `too_many_client_requests` at once, counted by the refusal penalty;
- a body must arrive at `min_rate` bytes per second on average from its request's arrival, after a grace of
  `grace_s` seconds (the next piece is awaited only until the body falls behind that line); else 408
  `body_too_slow`, counted by the refusal penalty, and the connection is closed.
"""

from __future__ import annotations

import asyncio
import itertools
import sys
import time
from collections import Counter
from collections.abc import Awaitable, Callable

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.http.auth import OPEN_PATHS
from service.http.errors import ApiError, client_of, penalise, send_refusal

# An ASGI extension of the request's scope: scope["extensions"]["rafd.arrival"] = {"at": time.monotonic() of the
# request's first byte (stamped by the server's protocol, service/http/head_limits.py; else on entry here), "number":
# its arrival number (set here)}.
ARRIVAL = "rafd.arrival"


def arrival_of(scope: Scope) -> tuple[float, int]:
    """The request's arrival key (at, number); now when IntakeMiddleware did not run (e.g. a bare router)."""
    arrival = scope.get("extensions", {}).get(ARRIVAL, {})
    if "number" not in arrival:
        return (time.monotonic(), 0)
    return (float(arrival["at"]), int(arrival["number"]))


async def _receive_within(receive: Receive, timeout: float) -> Message:
    if sys.version_info >= (3, 11):
        async with asyncio.timeout(timeout):
            return await receive()
    return await asyncio.wait_for(receive(), timeout)  # Python 3.10


class IntakeMiddleware:
    def __init__(self, app: ASGIApp, max_per_client: int, min_rate: int, grace_s: float, retry_after_s: int) -> None:
        self.app = app
        self.max_per_client = max_per_client
        self.min_rate = min_rate
        self.grace_s = grace_s
        self.retry_after_s = retry_after_s
        self.unfinished: Counter[str] = Counter()  # per client
        self._numbers = itertools.count(1)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        arrival = scope.setdefault("extensions", {}).setdefault(ARRIVAL, {})
        arrived_at = arrival.setdefault("at", time.monotonic())
        arrival["number"] = next(self._numbers)
        if scope["path"] in OPEN_PATHS:
            await self.app(scope, receive, send)
            return
        client = client_of(scope)
        if self.unfinished[client] >= self.max_per_client:
            await penalise(scope["app"], client)
            await self._refuse(send, has_body=_has_body(scope))
            return
        self.unfinished[client] += 1
        try:
            await self.app(scope, self._at_rate(receive, arrived_at) if self.min_rate else receive, send)
        finally:
            self.unfinished[client] -= 1
            if not self.unfinished[client]:
                del self.unfinished[client]

    def _at_rate(self, receive: Receive, arrived_at: float) -> Callable[[], Awaitable[Message]]:
        """`receive`, refusing a body that falls behind `min_rate` bytes/s (after the grace) since the arrival."""
        received = 0
        done = False

        async def receive_at_rate() -> Message:
            nonlocal received, done
            if done:
                return await receive()
            remaining = arrived_at + self.grace_s + received / self.min_rate - time.monotonic()
            try:
                if remaining <= 0:
                    raise asyncio.TimeoutError
                message = await _receive_within(receive, remaining)
            except asyncio.TimeoutError:
                raise ApiError(
                    "body_too_slow",
                    f"the body arrived slower than {self.min_rate} bytes/s (RAFD_MIN_BODY_BYTES_PER_S) after its "
                    f"first {self.grace_s:g} s: {received} bytes in {time.monotonic() - arrived_at:.1f} s",
                    headers={"Connection": "close"},
                ) from None
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                done = not message.get("more_body", False)
            else:
                done = True
            return message

        return receive_at_rate

    async def _refuse(self, send: Send, has_body: bool) -> None:
        await send_refusal(
            send,
            "too_many_client_requests",
            f"this client already has {self.max_per_client} unfinished requests "
            f"(RAFD_MAX_REQUESTS_PER_CLIENT); retry after {self.retry_after_s} s",
            headers={"Retry-After": str(self.retry_after_s)},
            close=has_body,  # not read: the connection closes after the answer (service/http/head_limits.py)
        )


def _has_body(scope: Scope) -> bool:
    for name, value in scope.get("headers", ()):
        if (name == b"content-length" and value.strip() not in (b"0", b"")) or name == b"transfer-encoding":
            return True
    return False
