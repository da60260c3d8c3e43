"""rafd-prepare ROOT CACHE: decode every scan of a data root once into memory-mapped centre crops (rafd.data.cache).

    rafd-prepare ROOT CACHE [--split NAME ...] [--crop PX] [--workers N] [--force]

Training and evaluation then read windows from CACHE (`rafd-train --cache CACHE`, `rafd-eval --cache CACHE`)
instead of decoding four full 1152 px PNGs per window. Sequences are prepared in parallel processes; a sequence
whose cache is complete (CACHE/<sequence>/cache.json) and matches its frames is skipped, so an interrupted run is
resumed by running the same command again. Exit status 0 on success, 2 on bad input, 1 if a sequence failed.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from rafd.data.cache import DEFAULT_CROP
from rafd.data.parallel import default_workers
from rafd.data.prepare import prepare_root


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="rafd-prepare", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("root", type=Path, help="data root holding RADIATE sequence folders (or one sequence)")
    parser.add_argument("cache", type=Path, help="cache root to write (mirrors the sequence folders)")
    parser.add_argument("--split", action="append", help="only these meta.json splits (repeat or comma-separate)")
    parser.add_argument(
        "--crop",
        type=int,
        default=DEFAULT_CROP,
        help=f"centre crop side in pixels (default {DEFAULT_CROP}: a 256 px input turned by any angle)",
    )
    parser.add_argument("--workers", type=int, default=default_workers(), help="parallel processes (default: CPUs)")
    parser.add_argument("--force", action="store_true", help="rebuild complete caches too")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        done = prepare_root(args.root, args.cache, args.split, args.crop, args.workers, args.force)
    except (FileNotFoundError, ValueError) as error:
        print(f"rafd-prepare: error: {error}", file=sys.stderr)
        return 2
    print(
        f"{args.cache}: {done.prepared} sequences prepared ({done.frames} frames, "
        f"{done.frames / max(done.seconds, 1e-9):.0f} frames/s), {done.skipped} already complete, in "
        f"{done.seconds:.1f} s"
    )
    for failure in done.failures:
        print(f"rafd-prepare: error: {failure}", file=sys.stderr)
    return 1 if done.failures else 0


if __name__ == "__main__":
    sys.exit(main())
