"""Slow answers to a client that keeps sending refused images, so a flood of bad files cannot eat the CPU.

A padded or broken PNG is refused from its chunk headers for well under a millisecond of server CPU, but a client
that sends them back to back gets its refusals so fast that it sends a thousand a second: on two cores the
refusals alone then take most of a core from the streams that send valid frames. A client (by address) refused
`after` times or more within the last second has each further refusal answered only after `delay_s`; a client
waits for its answer before it reuses the connection, so every connection it holds sends at most 1 / delay_s bad
files per second. Valid requests are never delayed, whoever sends them.
"""

from __future__ import annotations

import time
from collections import OrderedDict, deque
from collections.abc import Callable

WINDOW_S = 1.0  # refusals counted over this many seconds
MAX_CLIENTS = 4096  # addresses remembered (least recently refused forgotten first)


class RefusalPenalty:
    def __init__(self, delay_s: float, after: int, clock: Callable[[], float] = time.monotonic) -> None:
        self.delay_s = delay_s
        self.after = after
        self._clock = clock
        self._recent: OrderedDict[str, deque[float]] = OrderedDict()

    def record(self, client: str) -> float:
        """Count one refusal of `client` -> seconds to wait before answering it (0 when it is not flooding)."""
        if self.delay_s <= 0:
            return 0.0
        now = self._clock()
        times = self._recent.pop(client, None) or deque()
        while times and now - times[0] > WINDOW_S:
            times.popleft()
        times.append(now)
        self._recent[client] = times  # most recently refused last
        while len(self._recent) > MAX_CLIENTS:
            self._recent.popitem(last=False)
        return self.delay_s if len(times) > self.after else 0.0
