"""What the commands share: reading flags into the library's values."""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence


def split_names(values: Sequence[str]) -> tuple[str, ...]:
    """--split given repeated and/or comma-separated -> the split names in order."""
    return tuple(name.strip() for value in values for name in value.split(",") if name.strip())


def renamed(old: str, new: str, main: Callable[[Sequence[str] | None], int]) -> Callable[[Sequence[str] | None], int]:
    """An old command name kept for one release: warns (naming the new one) on stderr, then runs `main`."""

    def legacy_main(argv: Sequence[str] | None = None) -> int:
        print(f"{old}: deprecated name, use `{new}` (the same flags); {old} goes in the next release", file=sys.stderr)
        return main(argv)

    return legacy_main
