"""Progress bars for every job that takes more than a few seconds: one tqdm line per stage, saying what it does,
how far it is and how long it has left.

- `--quiet` (every long-running command, rafd.cli.flags.add_quiet) silences them all: `set_quiet(True)`.
- On a terminal a bar redraws in place. When stderr is not a terminal (CI logs, a file, a pipe) each bar writes
  at most one line per `LOG_INTERVAL_S` plus its last line, so an hour-long stage adds about a hundred lines to a
  log, never thousands.
- `stage(text)` is a stage without a count (exporting a graph, starting a server): one line when it starts.

tqdm is a core dependency (small, pure Python): the data tools use it without the train extra.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterable, Iterator
from typing import Any, TypeVar

from tqdm import tqdm

T = TypeVar("T")

LOG_INTERVAL_S = 30.0  # seconds between lines of a bar when stderr is not a terminal
_quiet = False


def set_quiet(quiet: bool) -> None:
    """Silence (True) or allow (False) every bar and stage line of this process."""
    global _quiet
    _quiet = bool(quiet)


def is_quiet() -> bool:
    return _quiet


def _interactive() -> bool:
    stream = sys.stderr
    return bool(getattr(stream, "isatty", lambda: False)()) and os.environ.get("TERM") != "dumb"


def bar(
    iterable: Iterable[T] | None = None,
    *,
    desc: str,
    total: float | None = None,
    unit: str = "it",
    enabled: bool = True,
    leave: bool = True,
    **options: Any,
) -> tqdm:
    """A tqdm bar on stderr, `desc` saying what the stage does; disabled with --quiet or `enabled=False`, and
    throttled to one line per LOG_INTERVAL_S when stderr is not a terminal."""
    interactive = _interactive()
    return tqdm(
        iterable,
        desc=desc,
        total=total,
        unit=unit,
        disable=_quiet or not enabled,
        leave=leave,
        dynamic_ncols=interactive,
        mininterval=0.1 if interactive else LOG_INTERVAL_S,
        maxinterval=10.0 if interactive else LOG_INTERVAL_S * 4,
        file=sys.stderr,
        **options,
    )


def track(
    iterable: Iterable[T], *, desc: str, total: float | None = None, unit: str = "it", enabled: bool = True
) -> Iterator[T]:
    """Iterate with a bar (see `bar`)."""
    with bar(iterable, desc=desc, total=total, unit=unit, enabled=enabled) as progress:
        yield from progress


class Stages:
    """A bar over a job's stages (one line): the stage running now, stages done of all, and the time left estimated
    from the stages done. `begin(text)` ends the stage before it."""

    def __init__(self, desc: str, total: int, enabled: bool = True) -> None:
        self.desc = desc
        self._bar = bar(desc=desc, total=total, unit="stage", enabled=enabled)
        self._running = False

    def begin(self, text: str) -> None:
        if self._running:
            self._bar.update(1)
        self._running = True
        self._bar.set_description_str(f"{self.desc}: {text}")

    def close(self) -> None:
        if self._running:
            self._bar.update(1)
            self._running = False
        self._bar.close()

    def __enter__(self) -> Stages:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def stage(text: str, enabled: bool = True) -> None:
    """One line on stderr saying which stage starts (for stages without a count); silent with --quiet."""
    if enabled and not _quiet:
        tqdm.write(f"[rafd] {text}", file=sys.stderr)
