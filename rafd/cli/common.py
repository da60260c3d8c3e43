"""What the commands share besides their flags (rafd.cli.flags): the old command names."""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence

from rafd.cli.flags import split_names

__all__ = ["renamed", "split_names"]


def renamed(old: str, new: str, main: Callable[[Sequence[str] | None], int]) -> Callable[[Sequence[str] | None], int]:
    """An old command name kept for one release: warns (naming the new one) on stderr, then runs `main`."""

    def legacy_main(argv: Sequence[str] | None = None) -> int:
        print(f"{old}: deprecated name, use `{new}` (the same flags); {old} goes in the next release", file=sys.stderr)
        return main(argv)

    return legacy_main
